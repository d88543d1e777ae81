"""`rigd serve` in its own process: it says where it listens, serves the console, and stops cleanly."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from rigd.app.testing.console import console_rig

REPO = Path(__file__).resolve().parents[4]


def _read_until_ready(proc: subprocess.Popen[str], deadline_s: float = 60.0) -> dict[str, str]:
    """The `name: value` lines `rigd serve` prints before `ready`."""
    assert proc.stdout is not None
    lines: dict[str, str] = {}
    deadline = time.monotonic() + deadline_s
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            pytest.fail(f"rigd serve exited ({proc.wait()}) before 'ready': {lines}")
        line = line.strip()
        if line == "ready":
            return lines
        name, sep, value = line.partition(": ")
        if sep:
            lines[name] = value
    pytest.fail(f"no 'ready' within {deadline_s} s: {lines}")


@pytest.mark.slow
def test_serve_prints_its_endpoints_serves_the_console_and_stops_cleanly(
    tmp_path: Path, runtime_dir: Path
) -> None:
    cfg = console_rig(tmp_path / "takes", runtime_dir)
    cfg_path = tmp_path / "rig.json"
    cfg_path.write_text(json.dumps(cfg.model_dump(mode="json")))
    proc = subprocess.Popen(
        [sys.executable, "-m", "rigd.app.cli", "serve", "--config", str(cfg_path), "--http", "127.0.0.1:0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        cwd=REPO,
        # No configured token (one is made), stdout not the journal (the login URL is printed).
        env={**{k: v for k, v in os.environ.items() if k != "JOURNAL_STREAM"}, "RIGD_HTTP_TOKEN": ""},
    )
    try:
        lines = _read_until_ready(proc)
        assert lines["control"] == cfg.service.control_endpoint
        assert lines["metrics"] == "off"
        login = lines["console"]  # the login URL, as Jupyter prints its own
        url, _, query = login.partition("?token=")
        assert url.startswith("http://127.0.0.1:")
        assert query
        assert not url.endswith(":0/")  # the port it got, not the one asked for
        assert httpx.get(url + "api/status", timeout=10).status_code == 401
        # `rigd console-url` prints the same URL again (for whoever can read the runtime dir).
        again = subprocess.run(
            [sys.executable, "-m", "rigd.app.cli", "console-url", "--connect", cfg.service.control_endpoint],
            capture_output=True,
            text=True,
            cwd=REPO,
            timeout=120,
        )
        assert (again.returncode, again.stdout.strip()) == (0, login), again.stderr
        # The login URL hands the secret to the tab's script (no cookie), which sends the header.
        with httpx.Client(timeout=10, headers={"x-rigd-token": query}) as browser:
            landed = browser.get(login)
            assert landed.status_code == 200
            assert "sessionStorage.setItem" in landed.text
            assert browser.get(url + "api/status").json()["state"] == "idle"
            # An open live stream must not hold the shutdown up.
            with browser.stream("GET", url + "api/live") as live:
                next(live.iter_lines())
                proc.send_signal(signal.SIGTERM)
                assert proc.wait(timeout=30) == 0
        # The login went with the daemon.
        assert not (runtime_dir / "console-login.json").exists()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_a_taken_console_port_stops_the_start_with_a_config_error(tmp_path: Path, runtime_dir: Path) -> None:
    """The console's port is bound like the daemon's other endpoints: taken, the daemon does not
    start (one line, exit 2 from `rigd serve`) and leaves nothing bound behind."""
    from rigd.app.console.server import ConsoleServer
    from rigd.app.service.daemon import Daemon
    from rigd.core.errors import ConfigError

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        cfg = console_rig(tmp_path / "takes", runtime_dir)
        daemon = Daemon(cfg, attachments=[ConsoleServer("127.0.0.1", port)])
        with pytest.raises(ConfigError, match=f"127.0.0.1:{port}: the console could not listen") as err:
            daemon.serve()
    assert "cannot bind" in str(err.value)
    assert "`rigd serve --http HOST:PORT` (port 0: any free port) or --no-http" in str(err.value)
    assert not Path(cfg.service.control_endpoint.removeprefix("ipc://")).exists()
