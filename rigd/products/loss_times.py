"""Loss records in the words of the take: times as seconds into the take, capped to its window.

A loss record keeps the device's own times (`t_first_us`, `t_last_us`, and in some reasons the
device counter it reached): that is what `--json` gives, exact and unmapped. A person reads
`did not deliver up to the end of the take window (device us 79005560 of 79538855)` as noise, and
`did not make 17.25 s of events` in a 5 s take as a contradiction. Here each record is said again
for people: its device times mapped through the device's clock fit (the sync report) to seconds
since the take's first pulse, never outside the take's window, and a span longer than the take
said as the take's length with the whole span beside it.

The records are written by the capture path (rigd.app.capture), whose reasons are fixed
sentences; the rewrites below match those sentences and leave any other text as it is.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from rigd.core.schema import LossRecord, SyncReport
from rigd.core.timebase import ClockMap

#: `(device us REACHED of END)` in "did not deliver up to the end of the take window ...".
_REACHED = re.compile(r"\(device us (-?\d+) of (-?\d+)\)")
#: "did not make 17.25 s of events": simulated time the sim skipped, over its whole run.
_SKIPPED = re.compile(r"did not make (\d+(?:\.\d+)?) s of events")


@dataclass(frozen=True, slots=True)
class TakeClock:
    """Device times -> seconds into the take (0 at the first pulse), capped to [0, length_s]."""

    report: SyncReport
    t0_us: int
    length_s: float

    @classmethod
    def of(cls, report: SyncReport | None) -> TakeClock | None:
        """The take's clock from its sync report; None without pulses (nothing to count from)."""
        if report is None or report.t_first_pulse_us is None or report.t_last_pulse_us is None:
            return None
        period_us = 1e6 / report.rate_hz if report.rate_hz > 0 else 0.0
        length = (report.t_last_pulse_us - report.t_first_pulse_us + period_us) / 1e6
        return cls(report, report.t_first_pulse_us, max(0.0, length))

    def seconds(self, device: str, device_us: int | None) -> float | None:
        """`device_us` of `device` as seconds into the take, capped to the window; None when the
        device has no clock fit or the time is unknown."""
        sync = self.report.devices.get(device)
        if device_us is None or sync is None:
            return None
        cmap = ClockMap(sync.device_ref_us, sync.rig_ref_us, sync.rate, sync.frac_us)
        rig_us = int(cmap.to_rig(device_us))
        return min(max((rig_us - self.t0_us) / 1e6, 0.0), self.length_s)

    def describe(self, rec: LossRecord) -> str:
        """The record's reason with its times in seconds of the take (module docstring)."""
        reason, when_said = rec.reason, False
        m = _REACHED.search(reason)
        if m:
            reached = self.seconds(rec.device, int(m.group(1)))
            if reached is not None:
                said = f"(reached {reached:.2f} s of the take's {self.length_s:.2f} s)"
                reason, when_said = reason[: m.start()] + said + reason[m.end() :], True
        m = _SKIPPED.search(reason)
        if m and float(m.group(1)) > self.length_s:
            said = (
                f"did not make up to {self.length_s:.2f} s of the take's events ({m.group(1)} s of "
                "simulated time in all, before and after the take too)"
            )
            reason = reason[: m.start()] + said + reason[m.end() :]
        if when_said:
            return reason
        first = self.seconds(rec.device, rec.t_first_us)
        last = self.seconds(rec.device, rec.t_last_us)
        if first is not None and last is not None:
            span = f"{first:.2f} s" if last - first < 0.005 else f"{first:.2f}-{last:.2f} s"
            return f"{reason} [at {span} of the take]"
        if first is not None:
            return f"{reason} [from {first:.2f} s of the take]"
        if last is not None:
            return f"{reason} [up to {last:.2f} s of the take]"
        return reason


def loss_lines(report: SyncReport | None, losses: list[LossRecord]) -> list[str]:
    """Each record's reason for people (TakeClock.describe), in the records' order."""
    clock = TakeClock.of(report)
    return [rec.reason if clock is None else clock.describe(rec) for rec in losses]
