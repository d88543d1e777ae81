"""Console security: remote binds need a token, every request needs it, cross-site posts are refused.

The login itself (every route, the login URL, other users) is tested in test_console_auth.py."""

from __future__ import annotations

from collections.abc import Callable

import pytest
from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.requests import Request
from starlette.responses import JSONResponse
from starlette.routing import Route
from starlette.testclient import TestClient

from rigd.app.console.security import (
    TOKEN_HEADER,
    ConsoleSecurity,
    SecurityMiddleware,
    cookie_name,
    parse_bind,
)
from rigd.app.console.server import ConsoleServer
from rigd.app.testing.console import ConsoleDaemon
from rigd.core.errors import ConfigError

TOKEN = "t0ken-for-the-console-tests"


def _app(security: ConsoleSecurity) -> TestClient:
    """A tiny app behind the middleware: what gets through is answered 200."""
    calls: list[str] = []

    async def ok(request: Request) -> JSONResponse:
        calls.append(request.method)
        return JSONResponse({"ok": True})

    app = Starlette(
        routes=[Route("/api/x", ok, methods=["GET", "POST"])],
        middleware=[Middleware(SecurityMiddleware, security=security)],
    )
    client = TestClient(app, base_url="http://127.0.0.1:8750")
    client.calls = calls
    return client


def test_remote_bind_without_token_refuses_to_start(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("RIGD_HTTP_TOKEN", raising=False)
    with pytest.raises(ConfigError, match="beyond loopback; that needs a token"):
        ConsoleServer("0.0.0.0", 8750)
    with pytest.raises(ConfigError, match="at least 16 characters"):
        ConsoleServer("0.0.0.0", 8750, token="short")
    assert ConsoleServer("0.0.0.0", 8750, token=TOKEN).security.token == TOKEN
    monkeypatch.setenv("RIGD_HTTP_TOKEN", TOKEN)
    assert ConsoleServer("192.168.1.5", 8750).security.token == TOKEN


def test_remote_bind_without_token_cli_exits_2(monkeypatch: pytest.MonkeyPatch) -> None:
    from typer.testing import CliRunner

    from rigd.app.cli import app

    monkeypatch.delenv("RIGD_HTTP_TOKEN", raising=False)
    r = CliRunner().invoke(app, ["serve", "--http", "0.0.0.0:8750", "--metrics-port", "-1"])
    assert r.exit_code == 2, r.output
    assert "needs a token" in r.output


def test_parse_bind() -> None:
    assert parse_bind("127.0.0.1:9000") == ("127.0.0.1", 9000)
    assert parse_bind(":9000") == ("127.0.0.1", 9000)
    assert parse_bind("[::1]:9000") == ("::1", 9000)
    assert parse_bind("localhost") == ("localhost", 8750)
    with pytest.raises(ConfigError):
        parse_bind("host:port")


def test_state_change_without_token_is_refused() -> None:
    client = _app(ConsoleSecurity.for_bind("127.0.0.1", TOKEN))
    assert client.get("/api/x").status_code == 401  # loopback is not authentication
    assert client.get("/api/x", headers={TOKEN_HEADER: TOKEN}).status_code == 200
    r = client.post("/api/x", json={})
    assert r.status_code == 401
    assert "rigd console-url" in r.json()["error"]["message"]
    assert client.post("/api/x", json={}, headers={TOKEN_HEADER: "wrong-token-xxxxxxxx"}).status_code == 401
    assert client.post("/api/x", json={}, headers={TOKEN_HEADER: TOKEN}).status_code == 200
    assert client.calls == ["GET", "POST"]


def test_cross_origin_and_form_posts_are_refused() -> None:
    client = _app(ConsoleSecurity.for_bind("127.0.0.1", TOKEN))
    ok = {TOKEN_HEADER: TOKEN}
    # A cross-site HTML form: form-encoded, foreign Origin, no token header: 401, a cookie or not.
    form = {"duration_s": "5"}
    assert client.post("/api/x", data=form, headers={"Origin": "http://evil.example"}).status_code == 401
    client.cookies.set(cookie_name(8750), TOKEN)  # a cookie never authenticates (not port-scoped)
    assert client.post("/api/x", data=form, headers={"Origin": "http://evil.example"}).status_code == 401
    client.cookies.clear()
    # Even with the token, a foreign origin or a form encoding is refused.
    assert client.post("/api/x", json={}, headers={**ok, "Origin": "http://evil.example"}).status_code == 403
    assert client.post("/api/x", data={"a": "1"}, headers=ok).status_code == 415
    plain = {**ok, "Content-Type": "text/plain"}
    assert client.post("/api/x", content=b"{}", headers=plain).status_code == 415
    assert client.post("/api/x", json={}, headers={**ok, "Sec-Fetch-Site": "cross-site"}).status_code == 403
    same = {**ok, "Origin": "http://127.0.0.1:8750"}
    assert client.post("/api/x", json={}, headers=same).status_code == 200
    assert client.calls == ["POST"]


def test_dns_rebinding_host_is_refused() -> None:
    client = _app(ConsoleSecurity.for_bind("127.0.0.1", TOKEN))
    ok = {TOKEN_HEADER: TOKEN}
    assert client.get("/api/x", headers={**ok, "Host": "attacker.example:8750"}).status_code == 421
    assert client.get("/api/x", headers={**ok, "Host": "localhost:8750"}).status_code == 200


def test_remote_console_needs_the_token_to_read() -> None:
    client = _app(ConsoleSecurity.for_bind("0.0.0.0", TOKEN))
    assert client.get("/api/x").status_code == 401
    assert client.get("/api/x", headers={TOKEN_HEADER: TOKEN}).status_code == 200
    # A cookie is sent to every port of the host: it never authenticates, not even a read.
    client.cookies.set(cookie_name(8750), TOKEN)
    assert client.get("/api/x").status_code == 401
    assert client.post("/api/x", json={}).status_code == 401


def test_console_of_a_daemon(console_daemon: Callable[..., ConsoleDaemon]) -> None:
    """Against a live daemon: /api/status is the telemetry document; a take cannot be started
    without the token or from a cross-site form, and the refused requests start nothing."""
    cd = console_daemon()
    with cd.http() as http:
        status = http.get("/api/status").json()
        assert status["state"] == "idle"
        assert {d["name"] for d in status["devices"]} == {"trigger", "cam0", "cam1", "cam2", "ev0", "ev1"}
        page = http.get("/").text
        assert cd.console.security.token not in page  # the tab keeps it; the page is public
        r = http.post("/api/takes/start", json={"duration_s": 1}, headers={TOKEN_HEADER: ""})
        assert r.status_code == 401
        r = http.post(
            "/api/takes/start",
            data={"duration_s": "1"},
            headers={"Origin": "http://evil.example", TOKEN_HEADER: cd.console.security.token},
        )
        assert r.status_code == 403
        # The control socket's own validation answers a bad request from the console too.
        tok = {TOKEN_HEADER: cd.console.security.token}
        r = http.post("/api/takes/start", json={"duration_s": -1}, headers=tok)
        assert r.status_code == 400
        assert r.json()["error"]["field"] == "args.duration_s"
        r = http.post("/api/takes/start", json={"label": "bad name!"}, headers=tok)
        assert r.status_code == 400
        assert r.json()["error"]["field"] == "args.label"
        r = http.post("/api/takes/stop", json={}, headers=tok)
        assert r.status_code == 409
        assert r.json()["error"]["code"] == "not_capturing"
        assert http.get("/api/status").json()["state"] == "idle"
        assert not list((cd.config.service.take_dir).glob("*.h5"))


def test_start_body_is_strict_like_the_control_socket(console_daemon: Callable[..., ConsoleDaemon]) -> None:
    cd = console_daemon()
    with cd.http() as http:
        for body, field in (
            ({"duration_s": "5"}, "duration_s"),
            ({"nope": 1}, "nope"),
            ({"notes": 3}, "notes"),
        ):
            r = http.post("/api/takes/start", json=body)
            assert r.status_code == 400, r.text
            assert r.json()["error"]["field"] == field
        assert http.post("/api/event-window", json={"window_ms": 15}).status_code == 400
        assert http.post("/api/event-window", json={"window_ms": 20}).json()["window_ms"] == 20
        assert http.get("/api/status").json()["state"] == "idle"
