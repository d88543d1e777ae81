"""Fixtures for the console tests: a daemon on a small sim rig with the web console attached."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from rigd.app.console.server import ConsoleServer
from rigd.app.service.daemon import Daemon
from rigd.app.testing.console import ConsoleDaemon, console_rig
from rigd.app.testing.daemon import serve_in_thread


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
