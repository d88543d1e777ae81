"""Fixtures of the app's tests: private runtime dirs and daemons on a small sim rig in a thread
(`rigd.app.testing.daemon` holds the helpers)."""

from __future__ import annotations

import os
import shutil
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from rigd.app.config import RigConfig
from rigd.app.service.client import DaemonClient
from rigd.app.service.daemon import Daemon
from rigd.app.testing.daemon import RunningDaemon, endpoints, serve_in_thread, small_rig


@pytest.fixture
def runtime_dir() -> Iterator[Path]:
    """A short private directory for IPC sockets (socket paths are limited to ~100 bytes)."""
    d = Path(tempfile.mkdtemp(prefix="rigd-t-"))
    os.chmod(d, 0o700)
    yield d
    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture
def start_daemon(runtime_dir: Path, tmp_path: Path) -> Iterator[object]:
    """Factory: start a Daemon in a thread on a small sim rig; stopped at teardown."""
    running: list[RunningDaemon] = []

    def start(config: RigConfig | None = None, **kw: object) -> RunningDaemon:
        cfg = config or small_rig(f"svc-{uuid.uuid4().hex[:6]}", take_dir=str(tmp_path / "takes"), **kw)
        data = cfg.model_dump(mode="json")
        data["service"].update(endpoints(runtime_dir))
        cfg = RigConfig.from_data(data)
        daemon = Daemon(cfg)
        th, errors = serve_in_thread(daemon, "daemon-under-test")
        client = DaemonClient(cfg.service.control_endpoint, timeout_s=10)
        rd = RunningDaemon(daemon, th, client, cfg, errors)
        running.append(rd)
        return rd

    yield start
    for rd in running:
        rd.client.close()
        rd.daemon.shutdown()
        rd.thread.join(timeout=60)
