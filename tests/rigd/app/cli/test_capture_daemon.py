"""`rigd capture` through the daemon: its stages as it runs, then the same summary as an in-process
capture."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import pytest
from typer.testing import CliRunner

from rigd.app.cli import app
from rigd.app.commands import capture as capture_command
from rigd.app.testing.daemon import RunningDaemon


@pytest.mark.slow
def test_capture_through_the_daemon_prints_the_summary_table(
    start_daemon: Callable[..., RunningDaemon],
) -> None:
    rd = start_daemon()
    endpoint = rd.config.service.control_endpoint
    r = CliRunner().invoke(app, ["capture", "--connect", endpoint, "--duration", "0.5"])
    assert r.exit_code == 0, r.output
    assert r.stdout.startswith("take: ")
    for heading in ("camera", "frames", "sync rms µs", "sensor", "events", "Mev/s"):
        assert heading in r.stdout, r.stdout
    for device in ("cam0", "cam1", "cam2", "ev0", "ev1"):
        assert device in r.stdout
    assert "status: complete" in r.stdout
    assert "wrote " in r.stdout


class _ScriptedDaemon:
    """A daemon client whose status answers walk through one take: capturing, stopping, done."""

    endpoint = "ipc:///run/rigd/control.sock"
    take = "/takes/rig-1.h5"

    def __init__(self) -> None:
        base: dict[str, Any] = {"take": self.take, "queue_depth": 3, "faults": [], "last_take": None}
        self.answers: list[dict[str, Any]] = [
            {**base, "state": "capturing", "pulses": 30, "take_elapsed_s": 1.0},
            {**base, "state": "capturing", "pulses": 60, "take_elapsed_s": 2.0},
            {**base, "state": "stopping", "pulses": 60, "take_elapsed_s": 2.2},
            {
                "state": "idle",
                "take": None,
                "last_take": {"path": self.take, "status": "complete", "bytes_written": 10},
            },
        ]

    def call(self, cmd: str, **_: Any) -> dict[str, Any]:
        if cmd == "capture":
            return {"take": self.take}
        return self.answers.pop(0) if len(self.answers) > 1 else self.answers[0]


def test_a_daemon_take_shows_its_capturing_and_stopping_stages(
    capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO)  # as `rigd -v`: off a terminal, a line per stage
    capture_command._capture_remote(_ScriptedDaemon(), 2.0, None, False)  # type: ignore[arg-type]
    err = capsys.readouterr().err
    stages = [line for line in err.splitlines() if line.startswith("capture (daemon): ")]
    assert stages[0] == "capture (daemon): capturing (2 s of pulses)"
    assert stages[1].startswith("capture (daemon): stopping: the daemon drains its queue")
    assert len(stages) == 2
