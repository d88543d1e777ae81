"""The end of acquisition: fix the take's last pulse and stop the box, wait (bounded) until every
device has delivered up to the end of the take window, stopping each that has, stop the others,
read what they still hold; then record what each delivered outside the window.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rigd.app.capture.channel import DeviceChannel, TriggerChannel
from rigd.app.capture.control import BoundedCalls, RunControl
from rigd.app.capture.faults import FaultBoard
from rigd.app.capture.ledger import LossLedger
from rigd.app.capture.window import TakeWindow

log = logging.getLogger(__name__)

#: A stop picks the take's last pulse at most this far ahead of the pulses seen, so the
#: window's end is known before the devices deliver data past it (the box is stopped at once;
#: the window ends at the earlier of its last pulse and this one).
STOP_LEAD_S = 0.1
#: What a thread still reading past the stop's read deadline, or closing the devices at the very
#: end, may take beyond the stop's own bound before it is left behind.
CLOSE_BOUND_S = 5.0


@dataclass(frozen=True, slots=True)
class StopWait:
    """How the stop's wait for the devices ended: `all_delivered` (every device delivered up to
    the end of the take window), else the bound (`writer.stop_backlog_s`) ran out with `behind`
    not there; `stuck`: devices whose stop did not return within the bound."""

    all_delivered: bool
    behind: tuple[str, ...]
    waited_s: float
    stuck: tuple[str, ...] = ()


class AcquisitionStop:
    """One take's stop, run by its control thread once the pulses are out or a stop came."""

    def __init__(
        self,
        path: Path,
        backlog_s: float,
        virtual: bool,
        window: TakeWindow,
        trigger: TriggerChannel,
        channels: Mapping[str, DeviceChannel[Any, Any]],
        control: RunControl,
        ledger: LossLedger,
        faults: FaultBoard,
    ) -> None:
        self.path = path
        self._backlog_s = backlog_s
        """`writer.stop_backlog_s`: the bound of each of the stop's waits."""
        self._virtual = virtual
        self._window = window
        self._trigger = trigger
        self._channels = channels
        self._control = control
        self._ledger = ledger
        self._faults = faults
        self._stops = BoundedCalls("device stop")

    def stop_devices(self, t_stop: float, behind: list[str], threads: list[threading.Thread]) -> StopWait:
        """Stop the devices still running (event sensors first), then let their acquisition
        threads read what they hold until the read deadline; how the stop's wait ended."""
        backlog_s = self._backlog_s
        t_waited = time.monotonic()
        for ch in sorted(self._channels.values(), key=lambda c: c.reading.stop_order):
            if ch.name not in self._stops:
                self._stops.start(ch.name, ch.stop)
        stuck = self._stops.join(t_waited + backlog_s)
        t_stopped = time.monotonic()
        delivered = not behind and self._control.first_error is None
        wait = StopWait(delivered, tuple(behind), t_waited - t_stop, tuple(stuck))
        read_deadline = t_stopped + backlog_s
        for ch in self._channels.values():
            ch.read_deadline = read_deadline
        self._control.acquiring_done.set()
        for th in threads:  # each ends at the read deadline (its reads time out)
            th.join(max(0.0, read_deadline - time.monotonic()) + CLOSE_BOUND_S)
            if th.is_alive():
                log.error("take %s: %s still reading past the stop bound; left behind", self.path, th.name)
        log.info(
            "take %s stop: %.2f s waiting for the window end (stopping each device that reached it), "
            "%.2f s stopping the others, %.2f s reading what they still held",
            self.path,
            t_waited - t_stop,
            t_stopped - t_waited,
            time.monotonic() - t_stopped,
        )
        return wait

    def stop_trigger(self) -> int:
        """Fix the take's last pulse and stop the box; the number of pulses of the take (those
        the box emitted, up to the last).

        The last pulse is chosen before STOP is sent, at most `STOP_LEAD_S` ahead of the
        pulses seen, so the devices' gates cut at a known end while the STOP round trip runs;
        the window then ends one period after the earlier of that pulse and the box's last."""
        window = self._window
        if self._trigger.device.follows:  # the box is another host's: its count fixes the end
            emitted = self._trigger.stop_box()
            last = window.last_index
            window.set_last_index(emitted - 1 if last is None else min(last, emitted - 1))
            return emitted if window.last_index is None else min(emitted, window.last_index + 1)
        lead = max(1, math.ceil(STOP_LEAD_S * self._window.rate_hz))
        ahead = max(window.seen_index, self._trigger.n_pulses - 1) + lead
        last = window.last_index
        window.set_last_index(ahead if last is None else min(last, ahead))
        emitted = self._trigger.stop_box()
        if emitted > 0:
            window.set_last_index(min(emitted - 1, window.last_index or 0))
        kept = emitted if window.last_index is None else min(emitted, window.last_index + 1)
        if kept < emitted:
            line = (
                f"the trigger box emitted {emitted - kept} pulse(s) after the take's last "
                f"(pulse {kept - 1}, fixed when the stop came); they are outside the take window"
            )
            log.info("take %s: %s", self.path, line)
            self._faults.note(line)
        log.info(
            "take %s: window %s..%s us (last pulse %s of %d emitted)",
            self.path,
            window.start_us,
            window.end_us,
            window.last_index,
            emitted,
        )
        return kept

    def wait_for_window(self) -> list[str]:
        """Until every device has delivered up to the end of the window (or is away), for at
        most `backlog_s`; the devices still behind then. A device that has is stopped at once
        (it makes nothing more for the take, and a loaded host gets its CPU back for the
        others), on its own thread (`BoundedCalls`). On virtual time the devices cannot fall
        behind, only the simulation be slow: the bound then counts from the last progress one
        of those still behind made, unless a signal asked for the stop (or a stop came while
        the take was stopping): then the wait ends at the bound."""
        control, backlog_s = self._control, self._backlog_s
        deadline = time.monotonic() + backlog_s
        progress: dict[str, int | None] = {}
        behind: list[str] = []
        while control.first_error is None:
            behind = []
            for name, ch in self._channels.items():
                if not ch.window_reached():
                    behind.append(name)
                elif name not in self._stops:
                    self._stops.start(name, ch.stop)
            if not behind:
                break
            if self._virtual and not control.hurry.is_set():
                now_progress = {
                    name: (gate.reached_us if (gate := self._channels[name].gate) is not None else None)
                    for name in behind
                }
                if any(progress.get(name) != reached for name, reached in now_progress.items()):
                    deadline = time.monotonic() + backlog_s
                progress = now_progress
            if time.monotonic() >= deadline:
                log.warning(
                    "take %s: %s not delivered up to the window end within writer.stop_backlog_s = %g s; "
                    "stopping anyway",
                    self.path,
                    ", ".join(behind),
                    backlog_s,
                )
                break
            time.sleep(0.02)
        return behind

    def record_window(self, wait: StopWait) -> dict[str, dict[str, int]]:
        """Per device, what it delivered outside the window (into the ledger's journal); a
        device that never delivered up to the window end gets a loss record for the span."""
        outside: dict[str, dict[str, int]] = {}
        backlog_s = self._backlog_s
        outside["trigger"] = {"before": 0, "after": self._trigger.pulses_after_window}
        self._ledger.set_outside("trigger", outside["trigger"])
        for name, ch in self._channels.items():
            gate = ch.gate
            if gate is None:
                continue
            outside[name] = gate.counts.as_dict()
            self._ledger.set_outside(name, outside[name])
            if gate.counts.total:
                log.info(
                    "%s: %d %s before and %d after the take window not written",
                    name,
                    gate.counts.before,
                    ch.what,
                    gate.counts.after,
                )
            if not ch.window_reached():
                reached, end = gate.still_to_come()
                clock = "host ns" if gate.mode == "host" else "device us"
                self._ledger.add(
                    name,
                    ch.what,
                    0,
                    f"did not deliver up to the end of the take window ({clock} {reached} of {end}) "
                    f"before it was stopped (writer.stop_backlog_s = {backlog_s:g} s); "
                    "the rest of its window is not in the take",
                    (reached, end) if gate.mode != "host" else (None, None),
                )
        for name in wait.stuck:
            ch = self._channels[name]
            line = (
                f"{name}: its stop did not return within writer.stop_backlog_s = {backlog_s:g} s; what it "
                "had not delivered by the read deadline is not in the take"
            )
            self._faults.note(line)
            self._ledger.add(
                name,
                ch.what,
                0,
                "stop did not return within writer.stop_backlog_s; the device was left running and "
                "what it had not delivered by then is not in the take (count unknown)",
                (None if ch.gate is None else ch.gate.reached_us, None),
            )
        return outside
