"""`rigd capture` through a daemon that stops answering: one line saying what happened and
where the take is, a non-zero exit, no traceback."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import typer

from rigd.app.commands.service import DAEMON_LOST_EXIT, capture_via_daemon
from rigd.app.service.client import DaemonClient, DaemonUnavailableError
from rigd.app.testing.daemon import REPO, endpoints, small_rig, spawn_daemon

TAKE = "/takes/rig-20261123-walk.h5"


class _Client:
    """A DaemonClient stand-in that goes away at a chosen call."""

    endpoint = "ipc:///run/rigd/control.sock"

    def __init__(self, dies_at: str, *, after: int = 0) -> None:
        self.dies_at = dies_at
        self.after = after
        self.calls: list[str] = []

    def call(self, cmd: str, **_: Any) -> dict[str, Any]:
        self.calls.append(cmd)
        if cmd == self.dies_at and self.calls.count(cmd) > self.after:
            raise DaemonUnavailableError(f"no reply from the daemon at {self.endpoint} within 2 s")
        if cmd == "capture":
            return {"take": TAKE, "pulses_total": 100}
        if cmd == "stop":
            return {"take": TAKE, "stopping": True}
        return {"state": "capturing", "take": TAKE, "last_take": None}


def _run(client: _Client, capsys: pytest.CaptureFixture[str], progress: Any = None) -> tuple[int, str]:
    with pytest.raises(typer.Exit) as exc:
        capture_via_daemon(client, 10.0, None, False, progress)  # type: ignore[arg-type]
    return exc.value.exit_code, capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.parametrize("after", [0, 1, 5])
def test_daemon_gone_while_following_the_take(after: int, capsys: pytest.CaptureFixture[str]) -> None:
    code, err = _run(_Client("status", after=after), capsys)
    assert code == DAEMON_LOST_EXIT != 0
    assert "stopped answering" in err, err
    assert TAKE in err, err
    assert "rigd recover" in err, err
    assert "Traceback" not in err


def test_daemon_gone_while_stopping_after_ctrl_c(capsys: pytest.CaptureFixture[str]) -> None:
    def interrupt(_: dict[str, Any]) -> None:
        raise KeyboardInterrupt

    code, err = _run(_Client("stop"), capsys, progress=interrupt)
    assert code == DAEMON_LOST_EXIT
    assert TAKE in err, err
    assert "rigd recover" in err, err


def test_daemon_gone_waiting_for_the_take_to_end_after_ctrl_c(capsys: pytest.CaptureFixture[str]) -> None:
    calls = {"n": 0}

    def interrupt_once(_: dict[str, Any]) -> None:
        calls["n"] += 1
        if calls["n"] == 1:
            raise KeyboardInterrupt

    code, err = _run(_Client("status", after=1), capsys, progress=interrupt_once)
    assert code == DAEMON_LOST_EXIT
    assert TAKE in err, err
    assert "rigd recover" in err, err


def test_daemon_gone_before_answering_capture(capsys: pytest.CaptureFixture[str]) -> None:
    code, err = _run(_Client("capture"), capsys)
    assert code == DAEMON_LOST_EXIT
    assert "did not answer the capture request" in err, err
    assert "rigd recover" in err, err


@pytest.mark.slow
def test_rigd_capture_daemon_killed_mid_take(runtime_dir: Path, tmp_path: Path) -> None:
    """End to end: `rigd capture` in its own process, the daemon SIGKILLed once the take runs."""
    cfg = small_rig("lost", take_dir=str(tmp_path / "takes"))
    daemon = spawn_daemon(cfg, runtime_dir, tmp_path / "daemon.log")
    control = endpoints(runtime_dir)["control"]
    cli = subprocess.Popen(
        [sys.executable, "-m", "rigd.app.cli", "capture", "--connect", control, "--duration", "600"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=REPO,
        env={**os.environ, "COLUMNS": "400"},
    )
    try:
        watcher = DaemonClient(control, timeout_s=5)
        deadline = time.monotonic() + 60
        take = None
        while take is None:
            assert time.monotonic() < deadline, "the take did not start"
            assert cli.poll() is None, cli.communicate()
            state = watcher.call("status")
            take = state["take"] if state["state"] == "capturing" else None
            time.sleep(0.1)
        watcher.close()
        os.kill(daemon.pid, signal.SIGKILL)
        daemon.wait(timeout=30)
        _, err_b = cli.communicate(timeout=120)
    finally:
        for p in (cli, daemon):
            if p.poll() is None:
                p.kill()
                p.wait()
    err = err_b.decode()
    assert cli.returncode == DAEMON_LOST_EXIT, err
    assert "Traceback" not in err, err
    assert take in err.replace("\n", ""), err
    assert "rigd recover" in err, err
