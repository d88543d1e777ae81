"""Runs the console's uvicorn server inside the daemon process, on its own thread and event loop.

Why in-process: the console reads the daemon's live state (latest frames, telemetry) without a
copy through a socket and answers requests with the daemon's own request handler. uvicorn runs on
a thread of its own (signal handling stays with the daemon's main thread) and is shut down by
setting `should_exit`, with a short grace for open live streams. Once it listens, its login (address
and secret) is written next to the control socket for `rigd console-url` (see `login.py`).
"""

from __future__ import annotations

import asyncio
import logging
import os
import threading
from pathlib import Path
from typing import Any

import uvicorn
from starlette.applications import Starlette

from rigd.app.console.app import ConsoleContext, build_app
from rigd.app.console.live import DEFAULT_RATE_HZ, DaemonSource, LivePublisher
from rigd.app.console.login import ConsoleLogin, login_path, remove_login, write_login
from rigd.app.console.security import ConsoleSecurity
from rigd.app.console.takes import TakeList
from rigd.core.errors import ConfigError

log = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8750
#: How long shutdown waits for browsers' open live streams before closing them.
_GRACE_S = 2.0
_START_TIMEOUT_S = 10.0


class ConsoleServer:
    """The web console of one daemon: `start(daemon)` binds and serves, `close()` stops."""

    def __init__(
        self,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        token: str | None = None,
        rate_hz: float = DEFAULT_RATE_HZ,
        guided_out: Path | None = None,
    ) -> None:
        self.security = ConsoleSecurity.for_bind(host, token)  # refuses a remote bind without token
        self.host = host
        self.port = port
        self.rate_hz = rate_hz
        self.guided_out = guided_out
        self.ctx: ConsoleContext | None = None
        self.app: Starlette | None = None
        self.login_file: Path | None = None
        self._server: uvicorn.Server | None = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    @property
    def login_url(self) -> str:
        """The address that logs a browser in (it carries the secret: show it to the operator only)."""
        return self.login().login_url

    def login(self) -> ConsoleLogin:
        return ConsoleLogin(url=self.url, token=self.security.token, pid=os.getpid())

    def start(self, daemon: Any) -> None:
        """Build the app for `daemon`, bind, serve on a thread; ConfigError if the port is taken."""
        from rigd.app.console.calibrate import GuidedController

        svc = daemon.config.service
        live = LivePublisher(DaemonSource(daemon), rate_hz=self.rate_hz, thumbnail_width=svc.thumbnail_width)
        takes = TakeList(svc.take_dir, svc.thumbnail_width)
        guided = GuidedController(daemon, live, self.guided_out or svc.take_dir / "calibration", takes)
        self.ctx = ConsoleContext(
            daemon=daemon,
            live=live,
            takes=takes,
            security=self.security,
            guided=guided,
        )
        app = self.app = build_app(self.ctx)
        config = uvicorn.Config(
            app,
            host=self.host,
            port=self.port,
            log_level="warning",
            lifespan="off",
            timeout_graceful_shutdown=int(_GRACE_S),
            access_log=False,
        )
        server = uvicorn.Server(config)
        self._server = server
        live.start()
        self._thread = threading.Thread(target=self._run, args=(server,), name="console-http", daemon=True)
        self._thread.start()
        deadline = threading.Event()
        for _ in range(int(_START_TIMEOUT_S / 0.02)):
            if server.started or not self._thread.is_alive():
                break
            deadline.wait(0.02)
        if not server.started:
            self.close()
            why = f": {self._error}" if self._error else ""
            raise ConfigError(
                f"--http {self.host}:{self.port}: the console could not listen{why}; give this daemon "
                "another address: `rigd serve --http HOST:PORT` (port 0: any free port) or --no-http"
            )
        sockets = [s for srv in server.servers for s in srv.sockets]
        if sockets:
            self.port = int(sockets[0].getsockname()[1])
        self.login_file = login_path(svc.control_endpoint)
        try:
            write_login(self.login_file, self.login())
        except ConfigError:
            self.close()
            raise
        log.info("console serving on %s (login URL in %s)", self.url, self.login_file)

    def _run(self, server: uvicorn.Server) -> None:
        try:
            asyncio.run(server.serve())
        except SystemExit as exc:  # uvicorn exits (code 3) when it cannot bind: said below
            log.debug("console server exited with %s", exc.code)
        except BaseException as exc:  # noqa: BLE001 - reported by start() or close(), with the cause
            self._error = exc
            log.error("console server stopped: %s", exc)
        if not server.started and self._error is None:
            # uvicorn reports a port it cannot bind by exiting; say which.
            self._error = OSError(f"cannot bind {self.host}:{self.port} (in use, or no permission)")

    def close(self) -> None:
        """Stop live streams and the server, remove the login file; idempotent."""
        if self.login_file is not None:
            remove_login(self.login_file, self.security.token)
            self.login_file = None
        if self.ctx is not None:
            self.ctx.closing.set()
            if self.ctx.guided is not None:
                self.ctx.guided.close()
            self.ctx.live.close()
        if self._server is not None:
            self._server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout=_GRACE_S + 5)
            if self._thread.is_alive():
                log.error("console server did not stop within %.0f s", _GRACE_S + 5)
        self._thread = None
