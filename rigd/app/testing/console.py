"""A daemon on a small sim rig with the web console attached, for the console's tests."""

from __future__ import annotations

import threading
import uuid
from dataclasses import dataclass
from pathlib import Path

import httpx

from rigd.app.config import RigConfig, default_sim_rig
from rigd.app.console.login import login_path, read_login
from rigd.app.console.security import TOKEN_HEADER
from rigd.app.console.server import ConsoleServer
from rigd.app.service.daemon import Daemon


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
    """A daemon serving in a thread with the web console attached."""

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
