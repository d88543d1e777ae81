"""Fixtures for the console tests: a daemon on a small sim rig with the web console attached."""

from __future__ import annotations

import os
import shutil
import tempfile
import threading
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest

from rigd.app.config import RigConfig, default_sim_rig
from rigd.app.console.login import login_path, read_login
from rigd.app.console.security import TOKEN_HEADER
from rigd.app.console.server import ConsoleServer
from rigd.app.service.daemon import Daemon
from tests.rigd.app.service.conftest import serve_in_thread


def console_rig(take_dir: Path, runtime: Path, *, resolution: tuple[int, int] = (160, 120)) -> RigConfig:
    """The default sim rig, small (2-core hosts), on private IPC endpoints, metrics off."""
    cfg = default_sim_rig(world=f"con-{uuid.uuid4().hex[:6]}", resolution=resolution, pixel_format="mono8")
    data = cfg.model_dump(mode="json")
    data["writer"]["disk_reserve_mb"] = 0
    data["writer"]["disk_ballast_mb"] = 24  # the minimum for this rig is about 20
    data["service"].update(
        {
            "metrics_port": None,
            "thumbnail_interval_s": 0.0,
            "telemetry_interval_s": 1.0,
            "take_dir": str(take_dir),
            "control": f"ipc://{runtime}/control.sock",
            "telemetry": f"ipc://{runtime}/telemetry.sock",
        }
    )
    return RigConfig.from_data(data)


@dataclass
class ConsoleDaemon:
    daemon: Daemon
    console: ConsoleServer
    thread: threading.Thread
    config: RigConfig

    @property
    def url(self) -> str:
        return self.console.url

    @property
    def login_url(self) -> str:
        """What `rigd console-url` prints for this daemon (read from its login file)."""
        return read_login(login_path(self.config.service.control_endpoint)).login_url

    @property
    def auth(self) -> dict[str, str]:
        """The header a program (not a browser) sends on every request."""
        return {TOKEN_HEADER: self.console.security.token}

    def http(self, timeout_s: float = 10.0) -> httpx.Client:
        """A client of this console that sends the secret with every request."""
        return httpx.Client(base_url=self.url.rstrip("/"), timeout=timeout_s, headers=self.auth)


@pytest.fixture
def runtime_dir() -> Iterator[Path]:
    d = Path(tempfile.mkdtemp(prefix="rigd-c-"))
    os.chmod(d, 0o700)
    yield d
    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture
def console_daemon(runtime_dir: Path, tmp_path: Path) -> Iterator[Callable[..., ConsoleDaemon]]:
    """Factory: a Daemon in a thread with a ConsoleServer on a free loopback port."""
    running: list[ConsoleDaemon] = []

    def start(resolution: tuple[int, int] = (160, 120), **console_kw: object) -> ConsoleDaemon:
        cfg = console_rig(tmp_path / "takes", runtime_dir, resolution=resolution)
        console = ConsoleServer("127.0.0.1", 0, **console_kw)  # type: ignore[arg-type]
        daemon = Daemon(cfg, attachments=[console])
        th, _ = serve_in_thread(daemon, "console-daemon")
        cd = ConsoleDaemon(daemon, console, th, cfg)
        running.append(cd)
        return cd

    yield start
    for cd in running:
        cd.daemon.shutdown()
        cd.thread.join(timeout=60)
