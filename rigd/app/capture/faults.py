"""The fault board and the watchdogs that post to it: trigger link, disk space, flushes.

A fault is active from the moment it is seen until it clears; cleared faults and other
events worth keeping (a clock re-tied, an unconfirmed STOP) go into the history, which the
take's warnings repeat.
"""

from __future__ import annotations

import logging
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path

from drivers.base import Trigger
from rigd.app.capture.control import RunControl, utc_now
from rigd.app.capture.results import ActiveFault
from rigd.core.errors import DeviceError, TakeError
from rigd.core.fault_codes import FaultCode

log = logging.getLogger(__name__)

#: How much later than its interval a flush may come before the writer counts as stalled.
FLUSH_STALL_SLACK_S = 2.0
#: A trigger link with no valid line for this long (at rates where pulses come faster) is silent.
TRIGGER_SILENT_S = 0.5

DiskUsage = Callable[[Path], "shutil._ntuple_diskusage"]


class FaultBoard:
    """Active faults by (code, device), and the history of what happened during the take."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._active: dict[tuple[str, str | None], ActiveFault] = {}
        self._history: list[str] = []

    def set(self, code: FaultCode, device: str | None, message: str) -> None:
        message = " ".join(message.split())  # one line: HDF5's messages span several
        with self._lock:
            if (code, device) in self._active:
                self._active[(code, device)].message = message
                return
            self._active[(code, device)] = ActiveFault(code, device, message, utc_now(), time.monotonic())
        log.error("fault %s%s: %s", code, f" ({device})" if device else "", message)

    def clear(self, code: FaultCode, device: str | None) -> None:
        with self._lock:
            fault = self._active.pop((code, device), None)
            if fault is not None:
                lasted = time.monotonic() - fault.since_mono
                self._history.append(fault.line(lasted))
        if fault is not None:
            log.warning("fault %s%s cleared after %.2f s", code, f" ({device})" if device else "", lasted)

    def is_active(self, code: str, device: str | None) -> bool:
        with self._lock:
            return (code, device) in self._active

    def active(self) -> list[ActiveFault]:
        with self._lock:
            return list(self._active.values())

    def note(self, line: str) -> None:
        """Something the take's warnings must say (a clock re-tied, an unconfirmed STOP)."""
        with self._lock:
            self._history.append(line)

    def history(self) -> list[str]:
        with self._lock:
            return list(self._history)

    def active_lines(self) -> list[str]:
        now = time.monotonic()
        return [f.line(now - f.since_mono) for f in self.active()]


class TriggerWatchdog:
    """Says within a second when the trigger link goes quiet or carries only garbage.

    Watches the driver's line counters; at rates too slow for the pulse records themselves
    to show silence in time, it asks the box for its count (a reply is a line)."""

    def __init__(
        self, trigger: Trigger, rate_hz: float, faults: FaultBoard, *, probe_always: bool = False
    ) -> None:
        self.trigger = trigger
        self.faults = faults
        #: Pulses come at a virtual world's pace, not the wall clock's: a quiet link is asked
        #: (COUNT?) whatever the rate, and only an unanswered question is a fault.
        self.probe_always = probe_always
        self.period_s = 1.0 / rate_hz
        self.threshold_s = (
            max(TRIGGER_SILENT_S, 2.5 * self.period_s) if self.period_s < 0.2 else TRIGGER_SILENT_S
        )
        self.lines = -1
        self.corrupt = 0
        self.line_mono = time.monotonic()
        self.corrupt_mono = 0.0
        self.probe: threading.Thread | None = None
        self.probe_failed: str | None = None

    def restart(self) -> None:
        """The pulses start now: silence counts from here."""
        self.line_mono = time.monotonic()

    def check(self) -> None:
        stats = self.trigger.link_stats()
        now = time.monotonic()
        lines, corrupt = int(stats.get("lines", 0)), int(stats.get("corrupt_lines", 0))
        if lines != self.lines:
            self.lines, self.line_mono = lines, now
            self.probe_failed = None
            self.faults.clear("trigger_silent", "trigger")
            self.faults.clear("trigger_garbage", "trigger")
        if corrupt != self.corrupt:
            self.corrupt, self.corrupt_mono = corrupt, now
        quiet = now - self.line_mono
        if quiet < self.threshold_s:
            return
        if self.corrupt_mono > self.line_mono:
            self.faults.set(
                "trigger_garbage",
                "trigger",
                f"the trigger link carries only garbage: {corrupt} corrupt lines so far, no valid line "
                f"for {quiet:.1f} s",
            )
            return
        if (
            self.period_s * 2.5 <= self.threshold_s and not self.probe_always
        ) or self.probe_failed is not None:
            why = f" ({self.probe_failed})" if self.probe_failed else ""
            self.faults.set(
                "trigger_silent",
                "trigger",
                f"no line from the trigger box for {quiet:.1f} s (a pulse record was due every "
                f"{self.period_s * 1e3:.0f} ms){why}",
            )
        elif self.probe is None or not self.probe.is_alive():
            self.probe = threading.Thread(target=self._probe, name="trigger-probe", daemon=True)
            self.probe.start()

    def _probe(self) -> None:
        try:
            self.trigger.pulse_count()
        except DeviceError as exc:
            self.probe_failed = f"COUNT? unanswered: {exc}"


class DiskWatch:
    """Free space against the reserve: refuse to start below it, stop the take cleanly when a
    running take goes below it."""

    def __init__(
        self,
        directory: Path,
        reserve_mb: int,
        faults: FaultBoard,
        control: RunControl,
        disk_usage: DiskUsage = shutil.disk_usage,
    ) -> None:
        self.directory = directory
        self.reserve = reserve_mb * 1_000_000
        self.faults = faults
        self.control = control
        self._disk_usage = disk_usage

    def check(self, *, preflight: bool = False) -> None:
        free = self._disk_usage(self.directory).free
        if free >= self.reserve:
            self.faults.clear("disk_low", None)
            return
        msg = (
            f"{free / 1e6:.0f} MB free in {self.directory}, below the reserve of {self.reserve / 1e6:.0f} MB"
        )
        if preflight:
            raise TakeError(f"not starting a take: {msg} (writer.disk_reserve_mb)")
        self.faults.set("disk_low", None, msg)
        self.control.request_stop(f"disk space low: {msg}", fault=True)


class FlushWatch:
    """A writer that stopped flushing (a hung disk or network mount) puts everything since at
    risk: say so long before the queue fills."""

    def __init__(self, interval_s: float, faults: FaultBoard) -> None:
        self.interval_s = interval_s
        self.faults = faults

    def check(self, now: float, since: float) -> None:
        """`since`: the last flush (or the start of the take, before the first)."""
        interval = self.interval_s
        if now - since > max(3 * interval, interval + FLUSH_STALL_SLACK_S):
            self.faults.set(
                "writer_stalled",
                None,
                f"no flush for {now - since:.1f} s (every {interval:g} s expected): the disk is not "
                "taking writes; a crash now would lose everything since",
            )
        else:
            self.faults.clear("writer_stalled", None)
