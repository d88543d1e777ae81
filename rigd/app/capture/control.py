"""How the threads of one take agree to stop: the stop request, fatal errors, guarded bodies."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from datetime import UTC, datetime

log = logging.getLogger(__name__)


def utc_now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


class RunControl:
    """Shared by the acquisition threads, the writer thread and the control thread.

    `acquiring_done` ends the acquisition loops; `stop_requested` asks the control thread to
    end the take (a user's stop, or the rig's own on a fault); `errors` holds what ended the
    take badly, re-raised by the control thread.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.acquiring_done = threading.Event()
        self.stop_requested = threading.Event()
        self.stop_reason: str | None = None
        self.stop_by_fault = False
        self._errors: list[BaseException] = []

    def request_stop(self, reason: str, *, fault: bool = False) -> None:
        """`fault`: the rig stopped itself (disk, trigger); the take's report says why."""
        with self._lock:
            if self.stop_reason is None:
                self.stop_reason = reason
                self.stop_by_fault = fault
        self.stop_requested.set()

    def fail(self, exc: BaseException) -> None:
        """A thread hit an error the take cannot go on with: stop acquiring; the control
        thread re-raises the first such error."""
        with self._lock:
            self._errors.append(exc)
        self.acquiring_done.set()

    @property
    def first_error(self) -> BaseException | None:
        with self._lock:
            return self._errors[0] if self._errors else None

    def guarded(self, name: str, body: Callable[[], None]) -> Callable[[], None]:
        """A thread body whose error, whatever it is, ends the take (recorded, re-raised by
        the control thread), never a thread that dies unseen."""

        def run() -> None:
            try:
                body()
            except BaseException as exc:  # recorded and re-raised by the control thread
                log.exception("capture thread %s failed", name)
                self.fail(exc)

        return run

    def start_thread(self, name: str, body: Callable[[], None], *, daemon: bool = True) -> threading.Thread:
        thread = threading.Thread(target=self.guarded(name, body), name=name, daemon=daemon)
        thread.start()
        return thread
