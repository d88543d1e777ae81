"""A browser that logged in to the console hands its secret to nobody else on the machine:
another local user listening on any loopback port, whose page the operator opens, receives no
cookie, header or address that holds it (cookies are not port-scoped; the console uses none)."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import textwrap
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from rigd.app.testing.console import ConsoleDaemon
from tests.rigd.app.console.browser import chromium_page

NOBODY = 65534

# Another user's listener: answers every request with a page that also asks its own origin for
# more, and writes down what each request carried. Standard library only (runs as nobody).
_LISTENER = textwrap.dedent(
    """
    import http.server, json, sys
    port, log = int(sys.argv[1]), sys.argv[2]
    PAGE = b"<!doctype html><title>hello</title><p id=p>hello</p><script>fetch('/more')</script>"
    class H(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            with open(log, "a") as f:
                f.write(json.dumps({"path": self.path, "headers": dict(self.headers)}) + "\\n")
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.end_headers()
            self.wfile.write(PAGE)
        def log_message(self, *a):
            pass
    http.server.HTTPServer(("127.0.0.1", port), H).serve_forever()
    """
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.slow
def test_a_logged_in_browser_sends_no_secret_to_another_loopback_port(
    console_daemon: Callable[..., ConsoleDaemon], request: pytest.FixtureRequest
) -> None:
    from playwright.sync_api import expect

    cd = console_daemon()
    token = cd.console.security.token
    scratch = Path(tempfile.mkdtemp(prefix="rigd-listener-"))
    scratch.chmod(0o1777)
    request.addfinalizer(lambda: shutil.rmtree(scratch, ignore_errors=True))
    log = scratch / "seen.jsonl"
    port = _free_port()
    cmd = [sys.executable, "-I", "-c", _LISTENER, str(port), str(log)]
    setpriv = shutil.which("setpriv")
    if os.geteuid() == 0 and setpriv is not None:  # as another uid, as the threat is
        cmd = [setpriv, f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups", *cmd]
    listener = subprocess.Popen(cmd)
    request.addfinalizer(lambda: (listener.kill(), listener.wait()))
    deadline = time.monotonic() + 30
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            break
        except OSError:
            assert time.monotonic() < deadline, "the listener did not start"
            time.sleep(0.05)
    with chromium_page() as page:
        page.goto(cd.login_url)
        assert page.url == cd.url  # the secret left the address bar
        expect(page.get_by_test_id("state")).to_have_text("idle")  # logged in: the header works
        cookies = page.context.cookies()
        # The operator follows a link to the other user's page on another loopback port.
        page.goto(f"http://127.0.0.1:{port}/welcome")
        expect(page.locator("#p")).to_have_text("hello")
        page.wait_for_function("performance.getEntriesByType('resource').length > 0")
        stolen = page.evaluate(
            "() => [sessionStorage.getItem('rigd-token'), localStorage.length, document.cookie]"
        )
        # Back to the console in the same tab: still logged in (the tab kept it, per origin).
        page.goto(cd.url)
        expect(page.get_by_test_id("state")).to_have_text("idle")
    seen = [json.loads(line) for line in log.read_text().splitlines()]
    assert {s["path"] for s in seen} >= {"/welcome", "/more"}
    assert not any(token in json.dumps(s) for s in seen), seen
    assert stolen == [None, 0, ""]
    assert not any(token in c["value"] for c in cookies)
