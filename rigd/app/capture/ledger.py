"""The loss ledger: every item the take did not get, with why, and the journal built from it.

Acquisition threads, the writer thread and the control thread all add to it; the writer
writes `journal()` into the take at every flush, so a crash loses none of the bookkeeping.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from rigd.app.capture.faults import FaultBoard
from rigd.core.schema import LossKind, LossRecord


class LossLedger:
    def __init__(self, faults: FaultBoard, trigger_link: Callable[[], dict[str, int]]) -> None:
        self._lock = threading.Lock()
        self._faults = faults
        self._trigger_link = trigger_link
        self._losses: list[LossRecord] = []
        self._failed: dict[str, str] = {}
        self._counters: dict[str, dict[str, int]] = {}
        self._outside: dict[str, dict[str, int]] = {}

    def add(
        self,
        device: str,
        what: LossKind,
        count: int,
        reason: str,
        t_range: tuple[int | None, int | None] = (None, None),
    ) -> None:
        record = LossRecord(
            device=device, what=what, count=count, reason=reason, t_first_us=t_range[0], t_last_us=t_range[1]
        )
        with self._lock:
            self._losses.append(record)

    def write_off(self, device: str, what: LossKind, why: str, t_last: int | None) -> None:
        """A device that failed for good: no data of it after `t_last` (device time)."""
        with self._lock:
            self._failed[device] = why
        self.add(device, what, 0, f"device failed mid-take; no data after this point: {why}", (t_last, None))

    def is_written_off(self, device: str) -> bool:
        with self._lock:
            return device in self._failed

    def written_off(self) -> dict[str, str]:
        with self._lock:
            return dict(self._failed)

    def set_counters(self, device: str, counters: dict[str, int]) -> None:
        with self._lock:
            self._counters[device] = dict(counters)

    def counters(self) -> dict[str, dict[str, int]]:
        with self._lock:
            return {k: dict(v) for k, v in self._counters.items()}

    def set_outside(self, device: str, counts: dict[str, int]) -> None:
        """What a device delivered outside the take's trigger window (not written, not lost)."""
        with self._lock:
            self._outside[device] = dict(counts)

    def outside(self) -> dict[str, dict[str, int]]:
        with self._lock:
            return {k: dict(v) for k, v in self._outside.items()}

    def records(self) -> list[LossRecord]:
        with self._lock:
            return list(self._losses)

    def lost_by_device(self) -> dict[str, int]:
        lost: dict[str, int] = {}
        with self._lock:
            for r in self._losses:
                lost[r.device] = lost.get(r.device, 0) + r.count
        return lost

    def journal(self) -> dict[str, Any]:
        """What the take must not lose if the process dies: the loss bookkeeping so far."""
        with self._lock:
            losses = [r.model_dump() for r in self._losses]
            failed = dict(self._failed)
            counters = {k: dict(v) for k, v in self._counters.items()}
            outside = {k: dict(v) for k, v in self._outside.items()}
        return {
            "outside_window": outside,
            "losses": losses,
            "failed_devices": failed,
            "device_counters": counters,
            "faults": self._faults.active_lines(),
            "fault_history": self._faults.history(),
            "trigger_link": self._trigger_link(),
        }
