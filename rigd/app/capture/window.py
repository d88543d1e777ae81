"""The take's trigger window; the gates that apply it to each device's data are in `gate`.

A take holds the data of its trigger window: from the first pulse minus
`writer.window_margin_us` to the last pulse plus one trigger period, in rig time (the trigger
box clock). The box reports pulse k at `b_k = b_0 + round(k * 1e6 / rate)`, so the window is
known relative to pulse 0 as soon as the last pulse index is (halves rounded up:
`rigd.core.timebase.pulse_offset_us`) (a fixed-duration take knows it
from the start; an open-ended one when the box is stopped).

Each gate (`gate.FrameGate`, `gate.EventGate`) applies the window in its device's own clock
while the take runs, so a device that delivers late (a loaded host, a backlog drained at stop)
cannot stretch the take:

* `trigger_in` (event sensor with trigger-in): the first rising edge is pulse 0; later edges
  are paired with pulse indices by rounding their distance from the previous paired edge in
  trigger periods (robust to dropped pulses and to drift, which accumulates only between
  consecutive edges); the window edges are placed in device time from the newest pair and
  the device clock rate measured between edges. Packets are split with `np.searchsorted`.
  Packets that arrive before the first edge are held (at most `window_hold_s` or
  `MAX_HELD_PACKETS`); without an edge by then the gate falls back to host time.
* `pulse_frames` (hardware-triggered camera with device timestamps): the first frame is
  pulse 0, later frames are paired the same way; a frame of a pulse after the last is
  outside.
* `host` (free-running or software-synced cameras, sensors without trigger-in, and the
  fallback): by the host arrival time of the frame against the host arrival times of the
  pulse records (approximate: the transport latency). An event packet is placed by its
  events' device times, mapped to the host clock by the earliest arrival seen (arrival minus
  newest device time, whose lower envelope a backlog cannot raise), so data read late is
  judged by when it happened.

What falls outside is not written and is counted (`OutsideCounts`): the take records it per
device (`window_outside_json`). A packet of EVT words across an edge is stored whole; finalize
counts its events outside the window by the final clock map (`stored_before`/`stored_after`).
Within the sync accuracy of each device the data in the file lies in [window_start_us,
window_end_us).
"""

from __future__ import annotations

import logging
import threading

import numpy as np
from numpy.typing import NDArray

from rigd.core.errors import RigdError
from rigd.core.timebase import pulse_offset_us

log = logging.getLogger(__name__)


class TakeWindow:
    """The rig-time bounds of a take; fed with the box's pulse records (thread-safe).

    Bounds relative to pulse 0 (`start_rel_us`, `end_rel_us`) are known without any pulse
    record; absolute ones need a pulse record (any index: `b_0` follows from the schedule).
    """

    def __init__(self, rate_hz: float, margin_us: int, last_index: int | None = None) -> None:
        if rate_hz <= 0:
            raise RigdError(f"trigger rate must be positive, got {rate_hz}")
        if margin_us < 0:
            raise RigdError(f"window margin must be >= 0 us, got {margin_us}")
        self.rate_hz = rate_hz
        self.period_us = 1e6 / rate_hz
        self.margin_us = int(margin_us)
        self._lock = threading.Lock()
        self._b0: int | None = None
        self._ref: tuple[int, int] | None = None  # newest (b_k, host_ns) of a pulse record
        self._last_index = last_index
        self._seen_index = -1

    def offset_us(self, k: int) -> int:
        """Box time of pulse k after pulse 0 (the box's schedule, no drift)."""
        return pulse_offset_us(k, self.rate_hz)

    def note_pulses(
        self, index: NDArray[np.int64], t_us: NDArray[np.int64], host_time_ns: NDArray[np.int64]
    ) -> None:
        """Pulse records as they arrive (any order, any gaps)."""
        if index.size == 0:
            return
        i = int(np.argmax(index))
        k, b, host = int(index[i]), int(t_us[i]), int(host_time_ns[i])
        with self._lock:
            if self._b0 is None:
                self._b0 = b - self.offset_us(k)
            if self._ref is None or b > self._ref[0]:
                self._ref = (b, host)
            self._seen_index = max(self._seen_index, k)

    @property
    def seen_index(self) -> int:
        """Highest pulse index reported so far (-1: none)."""
        with self._lock:
            return self._seen_index

    def set_last_index(self, k: int) -> None:
        """The last pulse of the take (0-based); the window ends one period after it."""
        with self._lock:
            self._last_index = max(0, int(k))

    @property
    def last_index(self) -> int | None:
        with self._lock:
            return self._last_index

    @property
    def first_pulse_us(self) -> int | None:
        with self._lock:
            return self._b0

    @property
    def start_rel_us(self) -> int:
        return -self.margin_us

    @property
    def end_rel_us(self) -> int | None:
        """Window end after pulse 0 in box us; None until the last pulse is known."""
        last = self.last_index
        return None if last is None else self.offset_us(last) + round(self.period_us)

    @property
    def start_us(self) -> int | None:
        b0 = self.first_pulse_us
        return None if b0 is None else b0 + self.start_rel_us

    @property
    def end_us(self) -> int | None:
        b0, end = self.first_pulse_us, self.end_rel_us
        return None if b0 is None or end is None else b0 + end

    def host_ns_at(self, rig_us: int) -> int | None:
        """Host monotonic ns when a pulse at `rig_us` would have been reported, from the
        newest pulse record (host latency of the records included)."""
        with self._lock:
            ref = self._ref
        if ref is None:
            return None
        return ref[1] + (rig_us - ref[0]) * 1000

    def host_bounds_ns(self) -> tuple[int | None, int | None]:
        start, end = self.start_us, self.end_us
        return (
            None if start is None else self.host_ns_at(start),
            None if end is None else self.host_ns_at(end),
        )
