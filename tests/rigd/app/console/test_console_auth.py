"""The console is at least as private as the control socket: every route needs the secret, the
secret is in the daemon's owner-only runtime directory, and another local user gets nowhere."""

from __future__ import annotations

import json
import os
import re
import shutil
import stat
import subprocess
import sys
import tempfile
import textwrap
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import httpx
import pytest
from starlette.routing import Mount, Route
from typer.testing import CliRunner

from rigd.app.cli import app as cli
from rigd.app.commands.service import Announcer
from rigd.app.console.login import ConsoleLogin, login_path, write_login
from rigd.app.console.security import TOKEN_HEADER, cookie_name
from rigd.app.testing.console import ConsoleDaemon

REPO = Path(__file__).resolve().parents[4]
NOBODY = 65534


def _requests(cd: ConsoleDaemon) -> list[tuple[str, str]]:
    """(method, path) of every route of the running console, from its route table: a route added
    later is in this list without anybody remembering to add it."""
    assert cd.console.app is not None
    out: list[tuple[str, str]] = []
    for route in cd.console.app.routes:
        if isinstance(route, Route):
            path = re.sub(r"\{(\w+)(:\w+)?\}", "x", route.path)
            out += [(m, path) for m in sorted(route.methods or {"GET"})]
        elif isinstance(route, Mount):
            out.append(("GET", route.path + "/common.js"))
        else:
            pytest.fail(f"a route of a kind this test does not know: {route!r}")
    return out


def _send(http: httpx.Client, method: str, path: str, **kw: object) -> httpx.Response:
    if path == "/api/live":  # a stream: its status line is the answer
        with http.stream(method, path, **kw) as resp:  # type: ignore[arg-type]
            return resp
    if method == "POST":
        # A body no handler accepts: what gets through is answered 4xx by the handler, not 401.
        return http.post(path, json={"no_such_field": 1}, **kw)  # type: ignore[arg-type]
    return http.request(method, path, **kw)  # type: ignore[arg-type]


@pytest.mark.slow
def test_every_route_needs_the_secret(console_daemon: Callable[..., ConsoleDaemon]) -> None:
    cd = console_daemon()
    requests = _requests(cd)
    paths = {p for _, p in requests}
    assert {"/", "/calibrate", "/api/status", "/api/live", "/api/takes/start", "/api/guided/start"} <= paths
    assert "/static/common.js" in paths
    origin = {"Origin": cd.url.rstrip("/")}
    wrong = {TOKEN_HEADER: "not-the-secret-of-this-console"}
    token = cd.console.security.token
    with httpx.Client(base_url=cd.url.rstrip("/"), timeout=30) as anon:
        for method, path in requests:
            page = path in ("/", "/calibrate") or path.startswith("/static/")
            public = method in ("GET", "HEAD") and page
            for headers in (origin, {**origin, **wrong}):
                r = _send(anon, method, path, headers=headers)
                if public:  # the same for everyone: no secret, no data
                    assert r.status_code == 200, (method, path, r.status_code)
                    assert token not in r.text
                else:
                    assert r.status_code == 401, (method, path, headers, r.status_code)
            # The right secret in a cookie is no login: only the header is.
            anon.cookies.set(cookie_name(cd.console.port), token)
            if not public:
                assert _send(anon, method, path, headers=origin).status_code == 401, (method, path)
            anon.cookies.clear()
    with cd.http(timeout_s=30) as http:
        for method, path in requests:
            r = _send(http, method, path, headers=origin)
            # Through to the handler: it answers (a bad body, nothing to preview, ...), never 5xx.
            assert r.status_code not in (401, 403, 415, 421), (method, path, r.status_code, r.text)
            assert r.status_code < 500, (method, path, r.status_code, r.text)
        status = http.get("/api/status").json()
    assert status["state"] == "idle"
    assert not list(cd.config.service.take_dir.glob("*.h5"))


def test_the_login_url_sets_no_cookie_and_hands_the_secret_to_the_tab(
    console_daemon: Callable[..., ConsoleDaemon],
) -> None:
    cd = console_daemon()
    token = cd.console.security.token
    assert cd.login_url == f"{cd.url}?token={token}"
    with httpx.Client(timeout=30) as browser:
        assert browser.get(cd.url + "?token=wrong-token-of-the-right-length").status_code == 401
        r = browser.get(cd.login_url.replace("/?", "/calibrate?") + "&x=1")
        assert r.status_code == 200
        assert r.headers["cache-control"] == "no-store"
        assert r.headers["referrer-policy"] == "no-referrer"
        # No cookie holds the secret (an expired one clears what an older console set).
        assert token not in r.headers.get("set-cookie", "")
        assert not browser.cookies
        assert f'sessionStorage.setItem("rigd-token", "{token}")' in r.text
        assert 'location.replace("/calibrate?x=1")' in r.text
        # The address it goes on to never leaves the console ("//host" would be another site).
        r = browser.get(cd.url + "/evil.example/?token=" + token)
        assert 'location.replace("/evil.example/")' in r.text
        assert browser.get(cd.url + "api/status").status_code == 401
        assert browser.get(cd.url + "api/status", headers={TOKEN_HEADER: token}).json()["state"] == "idle"
    assert not list(cd.config.service.take_dir.glob("*.h5"))


def test_the_login_is_kept_owner_only_and_leaves_with_the_daemon(
    console_daemon: Callable[..., ConsoleDaemon],
) -> None:
    cd = console_daemon()
    path = login_path(cd.config.service.control_endpoint)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    login = ConsoleLogin.model_validate_json(path.read_text())
    assert (login.url, login.token, login.pid) == (cd.url, cd.console.security.token, os.getpid())
    r = CliRunner().invoke(cli, ["console-url", "--connect", cd.config.service.control_endpoint])
    assert (r.exit_code, r.stdout.strip()) == (0, cd.login_url)
    cd.daemon.shutdown()
    cd.thread.join(timeout=60)
    assert not path.exists()
    r = CliRunner().invoke(cli, ["console-url", "--connect", cd.config.service.control_endpoint])
    assert r.exit_code == 3
    assert "no console login in" in r.output
    assert "Traceback" not in r.output


def test_console_url_says_when_the_login_is_stale(tmp_path: Path) -> None:
    """A daemon killed with SIGKILL leaves its login behind; its URL is not handed out as live."""
    run = tmp_path / "run"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    write_login(
        run / "console-login.json", ConsoleLogin(url="http://127.0.0.1:1/", token="t" * 32, pid=dead.pid)
    )
    r = CliRunner().invoke(cli, ["console-url", "--connect", f"ipc://{run}/control.sock"])
    assert r.exit_code == 3
    assert f"(pid {dead.pid}) that is no longer running" in r.output


def test_the_announcement_keeps_the_secret_out_of_the_journal(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """On a terminal the console line is the login URL; into the journal (which group adm reads)
    it is the bare address and where to get the login."""
    console = SimpleNamespace(url="http://127.0.0.1:8750/", login_url="http://127.0.0.1:8750/?token=s3cret")
    svc = SimpleNamespace(
        control_endpoint="ipc:///run/rigd/control.sock", telemetry_endpoint="t", take_dir="d"
    )
    daemon = SimpleNamespace(config=SimpleNamespace(service=svc), metrics_url=None)
    monkeypatch.delenv("JOURNAL_STREAM", raising=False)
    Announcer(console).start(daemon)
    assert "console: http://127.0.0.1:8750/?token=s3cret\n" in capsys.readouterr().out
    monkeypatch.setenv("JOURNAL_STREAM", "8:12345")
    Announcer(console).start(daemon)
    out = capsys.readouterr().out
    assert "s3cret" not in out
    assert "console: http://127.0.0.1:8750/ (login URL: rigd console-url)\n" in out


# What another local user tries with the secret's file and the console: read the file, drive the
# console without the secret or with a guess. Standard library only (it runs as nobody).
_OTHER_USER = textwrap.dedent(
    """
    import json, sys, urllib.error, urllib.request
    login_file, base = sys.argv[1:3]
    out = {}
    try:
        open(login_file).read()
        out["read"] = "read it"
    except OSError as exc:
        out["read"] = type(exc).__name__
    def call(method, path, body=None, headers=None):
        req = urllib.request.Request(base + path, data=body, method=method, headers=headers or {})
        try:
            with urllib.request.urlopen(req, timeout=60) as resp:
                return resp.status
        except urllib.error.HTTPError as exc:
            return exc.code
    start = json.dumps({"duration_s": 1}).encode()
    js = {"Content-Type": "application/json", "Origin": base}
    out["page"] = call("GET", "/")
    out["status"] = call("GET", "/api/status")
    out["start"] = call("POST", "/api/takes/start", start, js)
    out["start_guess"] = call("POST", "/api/takes/start", start, {**js, "X-Rigd-Token": "guess" * 8})
    out["login_guess"] = call("GET", "/?token=" + "guess" * 8)
    out["guided"] = call("POST", "/api/guided/start", b'{"camera": "cam0"}', js)
    print(json.dumps(out))
    """
)


@pytest.mark.slow
def test_another_user_can_neither_read_the_secret_nor_start_a_take(
    console_daemon: Callable[..., ConsoleDaemon], request: pytest.FixtureRequest
) -> None:
    """A local user who cannot open the 0700 control socket (uid 65534 here) gets nothing from the
    console either: not the secret, not `rigd console-url`, no data, not a take."""
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("setpriv (util-linux) is not installed: cannot run a client as another uid")
    if os.geteuid() != 0:
        pytest.skip("needs root to run a client as uid 65534 (setpriv --reuid)")
    as_nobody = [setpriv, f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups", sys.executable]
    cd = console_daemon()
    control = cd.config.service.control_endpoint
    # The CLI as another user needs a numba cache it may write (tmp_path is root's, 0700).
    numba_cache = Path(tempfile.mkdtemp(prefix="rigd-nobody-"))
    numba_cache.chmod(0o1777)
    request.addfinalizer(lambda: shutil.rmtree(numba_cache, ignore_errors=True))
    env = {
        **os.environ,
        "HOME": "/nonexistent",
        "PYTHONDONTWRITEBYTECODE": "1",
        "NUMBA_CACHE_DIR": str(numba_cache),
    }
    client = subprocess.run(
        [*as_nobody, "-I", "-c", _OTHER_USER, str(login_path(control)), cd.url.rstrip("/")],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert client.returncode == 0, client.stderr
    got = json.loads(client.stdout)
    assert got.pop("read") == "PermissionError"
    assert got.pop("page") == 200  # the page is the same for everyone: no secret in it
    assert got == dict.fromkeys(("status", "start", "start_guess", "login_guess", "guided"), 401)
    url = subprocess.run(
        [*as_nobody, "-m", "rigd.app.cli", "console-url", "--connect", control],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=REPO,
        env=env,
    )
    assert url.returncode == 2, url.stdout + url.stderr
    assert cd.console.security.token not in url.stdout + url.stderr
    assert "Traceback" not in url.stderr
    assert "permission denied" in url.stderr
    with cd.http() as http:
        assert http.get("/api/status").json()["state"] == "idle"
    assert not list(cd.config.service.take_dir.glob("*.h5"))
