"""A daemon whose start fails after its sockets are bound (an attachment such as the web console
could not start) leaves no thread behind: its telemetry thread stops before its socket closes."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from rigd.app.service.daemon import Daemon
from rigd.app.testing.daemon import endpoints, small_rig
from rigd.core.errors import ConfigError


class _Refuses:
    def start(self, daemon: Daemon) -> None:
        raise ConfigError("console: port 8750 is taken")

    def close(self) -> None:  # never started: nothing to close
        raise AssertionError("close() of an attachment that did not start")


def test_failed_attachment_stops_the_telemetry_thread(runtime_dir: Path, tmp_path: Path) -> None:
    ep = endpoints(runtime_dir)
    cfg = small_rig(
        "t-attach", take_dir=str(tmp_path / "takes"), control=ep["control"], telemetry=ep["telemetry"]
    )
    before = {t.ident for t in threading.enumerate()}
    with pytest.raises(ConfigError, match="port 8750 is taken"):
        Daemon(cfg, attachments=[_Refuses()]).serve()
    left = [t.name for t in threading.enumerate() if t.ident not in before and t.is_alive()]
    assert "telemetry" not in left, left
    assert not (runtime_dir / "control.sock").exists()
