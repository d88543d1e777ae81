"""Who may talk to the web console, and how a browser is kept from being used against it.

The console can start takes and write calibration files, so it is at least as private as the
control socket (an owner-only IPC socket): loopback is not authentication, since every local
user can connect to 127.0.0.1.

* Every request for data or action (`/api/...`) needs the console's secret in the
  `X-Rigd-Token` header, on loopback too; without it they answer 401. No cookie carries it:
  browsers send a cookie for 127.0.0.1 to every port of 127.0.0.1, so another local user's
  listener on any loopback port would receive it (cookies are not port-scoped). The pages
  (`/`, `/calibrate`) and their static code are the same for everyone, hold neither the secret
  nor data, and are served to anyone who can reach the console.
* The login URL (`/?token=...`, or any page with `?token=`) answers a small page that keeps
  the secret in the tab's sessionStorage, which is per origin (scheme, host and port), and
  replaces the address with the clean one; the console's script sends it as the header on
  every request: JSON, previews (fetched, shown as blob URLs) and the live stream (read
  through fetch, not EventSource, which cannot send a header). The secret is made at start (or
  given: `RIGD_HTTP_TOKEN`, `--http-token-file`) and kept for the operator in a 0600 file in
  the daemon's owner-only runtime directory (`login.py`); tokens are compared in constant time.
* It listens on loopback unless told otherwise; any other address needs an explicit token and
  the server refuses to start without one.
* Cross-site requests are refused: a POST must be JSON (a cross-site HTML form can only send
  form encodings or text/plain without a CORS preflight, which the console never grants), its
  Origin, when present, must be the console's own, and `Sec-Fetch-Site: cross-site` is refused.
* The Host header must name the console (a loopback name on loopback binds), so a DNS-rebound
  name cannot reach a loopback console from a web page.
"""

from __future__ import annotations

import hmac
import html
import json
import logging
import os
import secrets
from dataclasses import dataclass
from urllib.parse import urlencode, urlsplit

from starlette.requests import HTTPConnection
from starlette.responses import HTMLResponse, JSONResponse, Response
from starlette.types import ASGIApp, Receive, Scope, Send

from rigd.app.service.hosts import is_loopback
from rigd.core.errors import ConfigError

log = logging.getLogger(__name__)

TOKEN_ENV = "RIGD_HTTP_TOKEN"
TOKEN_HEADER = "x-rigd-token"
TOKEN_COOKIE = "rigd_token"
#: Tokens shorter than this are refused: the console must not be guessable.
MIN_TOKEN_CHARS = 16
_SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
_LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1", "[::1]"})
_NO_STORE = {"Cache-Control": "no-store"}


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


def cookie_name(port: int) -> str:
    """The login cookie of the console on `port`: browsers keep cookies per host, not per port,
    so two consoles on one machine must not overwrite each other's."""
    return f"{TOKEN_COOKIE}_{port}"


_LOGIN_HELP = (
    "this console needs its login URL: open the one `rigd serve` printed, "
    "or print it again with `rigd console-url`"
)


@dataclass(frozen=True)
class ConsoleSecurity:
    """The token and where the console listens (see the module docstring)."""

    host: str
    token: str

    @classmethod
    def for_bind(cls, host: str, token: str | None) -> ConsoleSecurity:
        """Refuse a remote bind without a token; on loopback make one when none is given."""
        token = token or os.environ.get(TOKEN_ENV) or None
        if token is not None and len(token) < MIN_TOKEN_CHARS:
            raise ConfigError(f"the console token must have at least {MIN_TOKEN_CHARS} characters")
        if not is_loopback(host) and token is None:
            raise ConfigError(
                f"--http {host}: the console listens beyond loopback; that needs a token "
                f"(--http-token-file or {TOKEN_ENV}) or a loopback address"
            )
        return cls(host, token or secrets.token_urlsafe(32))

    def token_ok(self, candidate: str | None) -> bool:
        """Constant-time comparison (no timing oracle on the secret)."""
        return candidate is not None and hmac.compare_digest(candidate.encode(), self.token.encode())

    def host_ok(self, host_header: str | None) -> bool:
        """Loopback binds answer only loopback names (no DNS rebinding); others any host (token)."""
        if host_header is None:
            return False
        if not is_loopback(self.host):
            return True
        name = urlsplit(f"//{host_header}").hostname or ""
        return name in _LOOPBACK_NAMES or is_loopback(name)

    def authenticated(self, conn: HTTPConnection) -> bool:
        """The request carries the secret in the header (never a cookie: see the module doc)."""
        return self.token_ok(conn.headers.get(TOKEN_HEADER))

    def refusal(self, conn: HTTPConnection) -> tuple[int, str] | None:
        """Why this request is refused (status, message), or None when it may go on."""
        if not self.host_ok(conn.headers.get("host")):
            return 421, "unknown Host for this console"
        if is_public(conn):
            return None
        if not self.authenticated(conn):
            return 401, _LOGIN_HELP
        method = conn.scope.get("method", "GET")
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
        if not self.token_ok(conn.headers.get(TOKEN_HEADER)):
            return 403, f"missing or wrong {TOKEN_HEADER} header"
        return None

    def login(self, conn: HTTPConnection) -> Response | None:
        """A GET with `?token=`: with the right one, a page that keeps the secret in the tab's
        sessionStorage and replaces the address with the same one without the token (out of the
        address bar and history); with a wrong one, 401. None for any other request. A login
        cookie an older console set for this port is deleted."""
        if conn.scope["type"] != "http" or conn.scope.get("method") not in ("GET", "HEAD"):
            return None
        candidate = conn.query_params.get("token")
        if candidate is None or not self.host_ok(conn.headers.get("host")):
            return None
        if not self.token_ok(candidate):
            return _refused(conn, 401, "wrong console token in the login URL; `rigd console-url` prints it")
        rest = urlencode([(k, v) for k, v in conn.query_params.multi_items() if k != "token"])
        path = "/" + conn.url.path.lstrip("/")  # "//host/x" would leave the console
        target = path + (f"?{rest}" if rest else "")
        page = _LOGIN_PAGE.format(
            token=_js_string(self.token), key=_js_string(TOKEN_STORAGE_KEY), target=_js_string(target)
        )
        headers = {**_NO_STORE, "Referrer-Policy": "no-referrer"}
        resp = HTMLResponse(page, 200, headers=headers)
        resp.delete_cookie(cookie_name(_port(conn)), path="/")
        return resp

    @staticmethod
    def _same_origin(origin: str, conn: HTTPConnection) -> bool:
        parts = urlsplit(origin)
        return parts.scheme in ("http", "https") and parts.netloc == conn.headers.get("host")


#: Pages and their code: the same for everyone, no secret, no data (served without the token).
_PUBLIC_PAGES = frozenset({"/", "/calibrate"})
#: Where the console's script keeps the secret (the tab's sessionStorage, per origin).
TOKEN_STORAGE_KEY = "rigd-token"
_LOGIN_PAGE = (
    "<!doctype html><title>rigd console</title><p>logging in…</p>"
    "<script>sessionStorage.setItem({key}, {token}); location.replace({target});</script>"
)


def is_public(conn: HTTPConnection) -> bool:
    """A page or static file (GET/HEAD): served to anyone, since it holds nothing private."""
    if conn.scope["type"] != "http" or conn.scope.get("method") not in ("GET", "HEAD"):
        return False
    path = conn.url.path
    return path in _PUBLIC_PAGES or path.startswith("/static/")


def _js_string(text: str) -> str:
    """`text` as a JavaScript string literal safe inside a <script> element."""
    return json.dumps(text).replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


def _port(conn: HTTPConnection) -> int:
    """The port the request came in on (the console's, also for port 0 binds)."""
    server = conn.scope.get("server") or ("", 0)
    return int(server[1] or 0)


def _refused(conn: HTTPConnection, status: int, message: str) -> Response:
    """JSON for programs; a short page for a person's browser (which asks for HTML)."""
    if "text/html" in conn.headers.get("accept", ""):
        page = f"<!doctype html><title>rigd console</title><p>{html.escape(message)}</p>"
        return HTMLResponse(page, status, headers=_NO_STORE)
    code = "unauthorized" if status == 401 else "forbidden"
    body = {"ok": False, "error": {"code": code, "message": message}}
    return JSONResponse(body, status, headers=_NO_STORE)


class SecurityMiddleware:
    """ASGI middleware: the login exchange, then `ConsoleSecurity.refusal` on every HTTP and
    WebSocket request."""

    def __init__(self, app: ASGIApp, security: ConsoleSecurity) -> None:
        self.app = app
        self.security = security

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        conn = HTTPConnection(scope)
        login = self.security.login(conn)
        if login is not None:
            log.info(
                "console login %s from %s",
                "refused" if login.status_code >= 400 else "accepted",
                scope.get("client"),
            )
            await login(scope, receive, send)
            return
        refused = self.security.refusal(conn)
        if refused is None:
            await self.app(scope, receive, send)
            return
        status, message = refused
        log.warning("console refused %s %s: %s", scope.get("method", "WS"), scope.get("path"), message)
        if scope["type"] == "websocket":
            await send({"type": "websocket.close", "code": 1008})
            return
        await _refused(conn, status, message)(scope, receive, send)
