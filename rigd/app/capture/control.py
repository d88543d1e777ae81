"""How the threads of one take agree to stop: the stop request, fatal errors, guarded bodies."""

from __future__ import annotations

import logging
import threading
import time
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
        self.stopping = False
        """The take has entered its stop (the control thread is ending it)."""
        self.hurry = threading.Event()
        """A signal asked for the stop, or a stop was asked for while the take was already
        stopping (after the end of a `--duration` take, say): the stop's waits end at their
        wall-clock bound, never later (not even on virtual time)."""
        self._errors: list[BaseException] = []

    def request_stop(self, reason: str, *, fault: bool = False, hurry: bool = False) -> None:
        """`fault`: the rig stopped itself (disk, trigger); the take's report says why. `hurry`
        (a signal): the stop's waits end at their wall-clock bound, never later."""
        with self._lock:
            if self.stop_reason is None:
                self.stop_reason = " ".join(reason.split())  # HDF5's messages span lines
                self.stop_by_fault = fault
            if self.stopping or hurry:
                self.hurry.set()
        self.stop_requested.set()

    def enter_stop(self) -> None:
        """The control thread starts ending the take; a stop asked for from now on hurries it."""
        with self._lock:
            self.stopping = True

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


class BoundedCalls:
    """Calls into devices (stop, close) run on helper threads, so one that does not return (a
    driver stuck in a wait) cannot keep a take from ending: `join` waits for them together, up
    to a deadline, and names those still running; they are left behind on daemon threads."""

    def __init__(self, what: str) -> None:
        self._what = what
        self._threads: dict[str, threading.Thread] = {}
        self._errors: list[BaseException] = []
        self._lock = threading.Lock()

    def __contains__(self, name: object) -> bool:
        return name in self._threads

    def start(self, name: str, body: Callable[[], None]) -> None:
        def run() -> None:
            try:
                body()
            except BaseException as exc:  # noqa: BLE001 - raised again by join, on the caller's thread
                with self._lock:
                    self._errors.append(exc)

        thread = threading.Thread(target=run, name=f"{self._what}-{name}", daemon=True)
        self._threads[name] = thread
        thread.start()

    def join(self, deadline: float) -> list[str]:
        """Wait until every call returned or the monotonic `deadline` passed; the names of the
        calls still running. The first error a call raised is raised here."""
        for thread in self._threads.values():
            thread.join(max(0.0, deadline - time.monotonic()))
        stuck = [name for name, th in self._threads.items() if th.is_alive()]
        if stuck:
            log.error("%s: %s did not return in time; left behind", self._what, ", ".join(stuck))
        with self._lock:
            if self._errors:
                raise self._errors[0]
        return stuck
