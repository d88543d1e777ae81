"""Who may talk to the web console, and how a browser is kept from being used against it.

The console can start takes and write calibration files, so it gets the same care as the
control socket:

* It listens on loopback unless told otherwise; any other address needs a token
  (`--http-token` or `RIGD_HTTP_TOKEN`) and the server refuses to start without one.
* Every state-changing request (POST) carries the token in the `X-Rigd-Token` header. On
  loopback without a configured token one is made at start; the page embeds it, so only a page
  the console served (same origin: other sites cannot read it) can use it.
* With a remote bind every request needs the token: the header, or the `rigd_token` cookie
  (HttpOnly, SameSite=Strict) that visiting `/?token=...` once sets.
* Cross-site requests are refused: a POST must be JSON (a cross-site HTML form can only send
  form encodings or text/plain without a CORS preflight, which the console never grants), its
  Origin, when present, must be the console's own, and `Sec-Fetch-Site: cross-site` is refused.
* The Host header must name the console (a loopback name on loopback binds), so a DNS-rebound
  name cannot reach a loopback console from a web page.
"""

from __future__ import annotations

import hmac
import ipaddress
import logging
import os
import secrets
from dataclasses import dataclass
from urllib.parse import urlsplit

from starlette.requests import HTTPConnection
from starlette.responses import JSONResponse, Response
from starlette.types import ASGIApp, Receive, Scope, Send

from rigd.core.errors import ConfigError

log = logging.getLogger(__name__)

TOKEN_ENV = "RIGD_HTTP_TOKEN"
TOKEN_HEADER = "x-rigd-token"
TOKEN_COOKIE = "rigd_token"
#: Tokens shorter than this are refused: a remote console must not be guessable.
MIN_TOKEN_CHARS = 16
_SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
_LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1", "[::1]"})


def is_loopback(host: str) -> bool:
    """True for loopback addresses and `localhost`."""
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def parse_bind(text: str, default_port: int = 8750) -> tuple[str, int]:
    """`HOST:PORT`, `HOST`, `:PORT` or `[V6]:PORT` -> (host, port)."""
    text = text.strip()
    if text.startswith("["):
        host, _, rest = text[1:].partition("]")
        port_text = rest.removeprefix(":")
    elif text.count(":") == 1:
        host, port_text = text.split(":")
    else:
        host, port_text = text, ""
    host = host or "127.0.0.1"
    try:
        port = int(port_text) if port_text else default_port
    except ValueError as exc:
        raise ConfigError(f"--http {text!r}: the port must be a number") from exc
    if not 0 <= port <= 65535:
        raise ConfigError(f"--http {text!r}: port {port} is out of range")
    return host, port


@dataclass(frozen=True)
class ConsoleSecurity:
    """The token and where the console listens (see the module docstring)."""

    host: str
    token: str
    token_required_to_read: bool

    @classmethod
    def for_bind(cls, host: str, token: str | None) -> ConsoleSecurity:
        """Refuse a remote bind without a token; on loopback make one when none is given."""
        token = token or os.environ.get(TOKEN_ENV) or None
        if token is not None and len(token) < MIN_TOKEN_CHARS:
            raise ConfigError(f"the console token must have at least {MIN_TOKEN_CHARS} characters")
        if not is_loopback(host):
            if token is None:
                raise ConfigError(
                    f"--http {host}: the console listens beyond loopback; that needs a token "
                    f"(--http-token or {TOKEN_ENV}) or a loopback address"
                )
            return cls(host, token, token_required_to_read=True)
        return cls(host, token or secrets.token_urlsafe(24), token_required_to_read=False)

    def token_ok(self, candidate: str | None) -> bool:
        return candidate is not None and hmac.compare_digest(candidate.encode(), self.token.encode())

    def host_ok(self, host_header: str | None) -> bool:
        """Loopback binds answer only loopback names (no DNS rebinding); others any host (token)."""
        if host_header is None:
            return False
        if not is_loopback(self.host):
            return True
        name = urlsplit(f"//{host_header}").hostname or ""
        return name in _LOOPBACK_NAMES or is_loopback(name)

    def refusal(self, conn: HTTPConnection) -> tuple[int, str] | None:
        """Why this request is refused (status, message), or None when it may go on."""
        if not self.host_ok(conn.headers.get("host")):
            return 421, "unknown Host for this console"
        method = conn.scope.get("method", "GET")
        token = conn.headers.get(TOKEN_HEADER)
        if self.token_required_to_read and not (
            self.token_ok(token)
            or self.token_ok(conn.cookies.get(TOKEN_COOKIE))
            or (method == "GET" and self.token_ok(conn.query_params.get("token")))
        ):
            return 401, "this console needs its token"
        if conn.scope["type"] != "http" or method in _SAFE_METHODS:
            return None
        if conn.headers.get("sec-fetch-site") == "cross-site":
            return 403, "cross-site request refused"
        origin = conn.headers.get("origin")
        if origin is not None and not self._same_origin(origin, conn):
            return 403, f"cross-origin request from {origin} refused"
        ctype = conn.headers.get("content-type", "").split(";")[0].strip().lower()
        if ctype != "application/json":
            return 415, "state-changing requests must be application/json"
        if not self.token_ok(token):
            return 403, f"missing or wrong {TOKEN_HEADER} header"
        return None

    @staticmethod
    def _same_origin(origin: str, conn: HTTPConnection) -> bool:
        parts = urlsplit(origin)
        return parts.scheme in ("http", "https") and parts.netloc == conn.headers.get("host")


class SecurityMiddleware:
    """ASGI middleware applying `ConsoleSecurity.refusal` to every HTTP and WebSocket request."""

    def __init__(self, app: ASGIApp, security: ConsoleSecurity) -> None:
        self.app = app
        self.security = security

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        conn = HTTPConnection(scope)
        refused = self.security.refusal(conn)
        if refused is None:
            await self.app(scope, receive, send)
            return
        status, message = refused
        log.warning("console refused %s %s: %s", scope.get("method", "WS"), scope.get("path"), message)
        if scope["type"] == "websocket":
            await send({"type": "websocket.close", "code": 1008})
            return
        body = {"ok": False, "error": {"code": "forbidden", "message": message}}
        response: Response = JSONResponse(body, status)
        await response(scope, receive, send)
