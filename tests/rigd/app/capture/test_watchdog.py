"""The trigger watchdog: a quiet link is a fault on real time, a question on virtual time."""

from __future__ import annotations

import time
from typing import Any

from rigd.app.capture.faults import FaultBoard, TriggerWatchdog


class QuietBox:
    """A trigger whose link has carried no line since the watchdog last looked; it answers."""

    def __init__(self) -> None:
        self.asked = 0

    def link_stats(self) -> dict[str, int]:
        return {"lines": 5, "corrupt_lines": 0}

    def pulse_count(self) -> int:
        self.asked += 1
        return 5


def _quiet_for(wd: TriggerWatchdog, seconds: float) -> None:
    wd.check()  # takes in the line count
    wd.line_mono = time.monotonic() - seconds  # the last line came that long ago


def test_real_time_silence_at_30_hz_is_a_fault() -> None:
    faults, box = FaultBoard(), QuietBox()
    wd = TriggerWatchdog(box, 30.0, faults)  # type: ignore[arg-type]
    _quiet_for(wd, 2.0)
    wd.check()
    assert [f.code for f in faults.active()] == ["trigger_silent"]
    assert box.asked == 0


def test_on_virtual_time_a_quiet_link_is_asked_and_an_answer_is_no_fault() -> None:
    faults, box = FaultBoard(), QuietBox()
    wd = TriggerWatchdog(box, 30.0, faults, probe_always=True)  # type: ignore[arg-type]
    _quiet_for(wd, 2.0)
    wd.check()
    assert wd.probe is not None
    wd.probe.join(5)
    assert box.asked == 1
    assert faults.active() == []
    wd.check()  # the answer left no failure behind: still no fault
    assert faults.active() == []


def test_on_virtual_time_an_unanswered_question_is_a_fault() -> None:
    from rigd.core.errors import DeviceError

    class DeadBox(QuietBox):
        def pulse_count(self) -> Any:
            raise DeviceError("COUNT? timed out")

    faults = FaultBoard()
    wd = TriggerWatchdog(DeadBox(), 30.0, faults, probe_always=True)  # type: ignore[arg-type]
    _quiet_for(wd, 2.0)
    wd.check()
    assert wd.probe is not None
    wd.probe.join(5)
    wd.check()
    assert [f.code for f in faults.active()] == ["trigger_silent"]
