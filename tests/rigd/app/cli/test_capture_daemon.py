"""`rigd capture` through the daemon prints the same summary as an in-process capture."""

from __future__ import annotations

from collections.abc import Callable

from typer.testing import CliRunner

from rigd.app.cli import app
from tests.rigd.app.service.conftest import RunningDaemon, runtime_dir, start_daemon  # noqa: F401


def test_capture_through_the_daemon_prints_the_summary_table(
    start_daemon: Callable[..., RunningDaemon],  # noqa: F811
) -> None:
    rd = start_daemon()
    endpoint = rd.config.service.control_endpoint
    r = CliRunner().invoke(app, ["capture", "--connect", endpoint, "--duration", "0.5"])
    assert r.exit_code == 0, r.output
    assert r.stdout.startswith("take: ")
    for heading in ("camera", "frames", "sync rms us", "sensor", "events", "Mev/s"):
        assert heading in r.stdout, r.stdout
    for device in ("cam0", "cam1", "cam2", "ev0", "ev1"):
        assert device in r.stdout
    assert "status: complete" in r.stdout
    assert "wrote " in r.stdout
