"""Daemons on a small sim rig for the tests and benchmarks: the rig's config, a daemon in a
thread or in a `rigd serve` process (for the kill and memory tests), its private endpoints."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from rigd.app.config import RigConfig, default_sim_rig
from rigd.app.service.client import DaemonClient, find_daemon
from rigd.app.service.daemon import Daemon

#: The checkout a `rigd serve` subprocess runs in.
REPO = Path(__file__).resolve().parents[3]


def small_rig(
    world: str,
    *,
    extra: dict[str, str] | None = None,
    clock: Literal["real", "virtual"] = "real",
    **service: object,
) -> RigConfig:
    """The default sim rig at 160x120 (fast enough for many takes on 2 cores).

    `extra` appends query parameters to one device's spec: {"cam1": "unplug_at_s=1"}. `clock`
    "virtual": the rig loses nothing to a loaded host (a test of what a take holds)."""
    cfg = default_sim_rig(world=world, resolution=(160, 120), clock=clock)
    data = cfg.model_dump(mode="json")
    for dev in [*data["cameras"], *data["event_sensors"]]:
        if extra and dev["name"] in extra:
            dev["spec"] += "&" + extra[dev["name"]]
    if extra and "trigger" in extra:
        data["trigger"]["spec"] += "&" + extra["trigger"]
    data["writer"]["disk_reserve_mb"] = 0
    data["writer"]["disk_ballast_mb"] = 24  # above this rig's minimum (about 11 MB)
    data["service"].update({"metrics_port": None, "thumbnail_interval_s": 0.5, "telemetry_interval_s": 0.2})
    data["service"].update(service)
    return RigConfig.from_data(data)


@dataclass
class RunningDaemon:
    """A daemon serving in a thread, a client of it, its config and its thread's errors."""

    daemon: Daemon
    thread: threading.Thread
    client: DaemonClient
    config: RigConfig
    errors: list[BaseException]


def endpoints(runtime: Path) -> dict[str, str]:
    """The control and telemetry endpoints of a daemon whose sockets are in `runtime`."""
    return {"control": f"ipc://{runtime}/control.sock", "telemetry": f"ipc://{runtime}/telemetry.sock"}


def serve_in_thread(daemon: Daemon, name: str) -> tuple[threading.Thread, list[BaseException]]:
    """`daemon.serve()` in a daemon thread, returned once it is ready (a start-up error is raised);
    later errors are collected in the returned list for the test to surface."""
    errors: list[BaseException] = []

    def run() -> None:
        try:
            daemon.serve()
        except BaseException as exc:  # noqa: BLE001 - surfaced by the test through `errors`
            errors.append(exc)

    th = threading.Thread(target=run, name=name, daemon=True)
    th.start()
    deadline = time.monotonic() + 30
    while not daemon.wait_ready(0.1):
        if errors:
            raise errors[0]
        assert time.monotonic() < deadline, "daemon did not become ready"
    return th, errors


def wait_idle(client: DaemonClient, timeout: float = 60.0) -> dict[str, object]:
    """The daemon's status once it is idle again (its take ended)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        t = client.call("status")
        if t["state"] == "idle":
            return t
        time.sleep(0.1)
    raise AssertionError("daemon did not go back to idle")


def spawn_daemon(
    config: RigConfig, runtime: Path, log_path: Path, env: dict[str, str] | None = None
) -> subprocess.Popen[bytes]:
    """`rigd serve` in its own process (for SIGKILL and memory tests), its console on a free port
    so that daemons of tests running side by side never collide on the default one."""
    cfg_path = runtime / f"rig-{uuid.uuid4().hex[:6]}.json"
    data = config.model_dump(mode="json")
    data["service"].update(endpoints(runtime))
    cfg_path.write_text(json.dumps(data))
    full_env = {**os.environ, **(env or {})}
    log = log_path.open("ab")
    proc = subprocess.Popen(
        [sys.executable, "-m", "rigd.app.cli", "serve", "--config", str(cfg_path), "--http", "127.0.0.1:0"],
        stdout=log,
        stderr=subprocess.STDOUT,
        env=full_env,
        cwd=REPO,
    )
    deadline = time.monotonic() + 60
    endpoint = endpoints(runtime)["control"]
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise AssertionError(f"daemon exited with {proc.returncode}: {log_path.read_text()[-2000:]}")
        client = find_daemon(endpoint, timeout_s=0.5)
        if client is not None:
            client.close()
            return proc
        time.sleep(0.1)
    proc.kill()
    raise AssertionError(f"daemon did not answer: {log_path.read_text()[-2000:]}")
