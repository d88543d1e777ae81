"""`run_capture`: one take, blocking, for a command line or a script; signals stop it cleanly
(`StopOnSignals`)."""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Callable, Iterable
from pathlib import Path
from types import FrameType
from typing import Any

from rigd.app.capture.results import CaptureResult, Progress
from rigd.app.capture.session import CaptureSession
from rigd.app.config import RigConfig

log = logging.getLogger(__name__)


class StopOnSignals:
    """While active (main thread only), the given signals stop the session as a user's stop
    does: the take is drained and finalized. A second signal raises KeyboardInterrupt, which
    abandons the take unfinished (`rigd recover` seals it)."""

    def __init__(self, session: CaptureSession, signals: Iterable[int]) -> None:
        self._session = session
        self._signals = list(signals)
        self._previous: dict[int, Any] = {}
        self.received: int | None = None

    def __enter__(self) -> StopOnSignals:
        if threading.current_thread() is threading.main_thread():
            for sig in self._signals:
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        name = signal.Signals(signum).name
        if self.received is not None:
            log.error("%s again while the take was being finalized: abandoning %s", name, self._session.path)
            raise KeyboardInterrupt
        self.received = signum
        log.warning(
            "%s: stopping take %s; it is finalized as usual (again to abandon it)", name, self._session.path
        )
        self._session.request_stop(f"{name} received", hurry=True)


def run_capture(
    config: RigConfig,
    out_dir: Path,
    duration_s: float,
    *,
    on_progress: Callable[[Progress], None] | None = None,
    path: Path | None = None,
    label: str | None = None,
    reconnect_interval_s: float | None = None,
    stop_signals: Iterable[int] = (),
) -> CaptureResult:
    """Capture one take of `duration_s` seconds of trigger pulses and return its summary.

    `stop_signals` (e.g. SIGINT, SIGTERM, SIGHUP for a command line) end the take early and
    cleanly; the result then says which one (`stop_signal`). Without them a KeyboardInterrupt
    still stops and finalizes the take before it propagates."""
    session = CaptureSession(
        config,
        out_dir,
        duration_s=duration_s,
        path=path,
        label=label,
        reconnect_interval_s=reconnect_interval_s,
    )
    session.start()
    with StopOnSignals(session, stop_signals) as signals:
        try:
            while (result := session.wait(0.05)) is None:
                if on_progress:
                    on_progress(session.progress())
        except KeyboardInterrupt:
            if signals.received is None:
                session.request_stop("interrupted")
                session.wait()
            raise
    if on_progress:
        on_progress(session.progress())
    result.stop_signal = signals.received
    return result
