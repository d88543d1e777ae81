"""The gate each device's data passes through on its way to the writer: what lies outside the
take's trigger window (`window.TakeWindow`) is counted, not written.

Each gate applies the window in its device's own clock while the take runs, so a device that
delivers late (a loaded host, a backlog drained at stop) cannot stretch the take. One gate per
device kind (`FrameGate`, `EventGate`; the modes are described in `window`): the channel hands
every item to its gate without asking what it is.
"""

from __future__ import annotations

import logging
import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Generic, Literal, TypeVar

import numpy as np
from numpy.typing import NDArray

from rigd.app.capture.window import TakeWindow
from rigd.core.events import EventPacket
from rigd.core.frames import Frame
from rigd.core.host_clock import MONOTONIC

log = logging.getLogger(__name__)

GateMode = Literal["trigger_in", "pulse_frames", "host"]
#: Packets a gate holds at most while it waits for its sensor's first trigger edge.
MAX_HELD_PACKETS = 5000
#: Host mode: an event packet mapping further behind its arrival than this is judged by its
#: arrival (above the overload shedder's lag bound; a device clock that jumped back).
MAX_MAPPED_LAG_NS = 30_000_000_000

ItemT = TypeVar("ItemT", Frame, EventPacket)


@dataclass(slots=True)
class OutsideCounts:
    """What a gate kept out of the take: items (events or frames) and trigger edges."""

    before: int = 0
    after: int = 0
    triggers_before: int = 0
    triggers_after: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)

    @property
    def total(self) -> int:
        return self.before + self.after


class WindowGate(ABC, Generic[ItemT]):
    """One device's filter: `admit` returns what of an item lies in the take's window. The
    kind's gate (`FrameGate`, `EventGate`) places items in its device's clock; placing by host
    time is common to both.

    Called from the device's acquisition thread only; `closed`, `counts` and `reached_us`
    are read by the control thread (plain attribute reads). `clock_ns` reads the clock the
    items' host times are on (the take's host clock): it times the hold for a first trigger
    edge, so on virtual time the hold is `hold_s` of the world's time, not of the machine's.
    """

    def __init__(
        self,
        name: str,
        mode: GateMode,
        window: TakeWindow,
        *,
        trigger_channel: int = 0,
        hold_s: float = 5.0,
        max_held: int = MAX_HELD_PACKETS,
        clock_ns: Callable[[], int] = MONOTONIC.now_ns,
    ) -> None:
        self.name = name
        self.mode: GateMode = mode
        self.window = window
        self.counts = OutsideCounts()
        self.closed = False
        """The device delivered data at or past the window end (nothing of the window is
        still to come from it)."""
        self.reached_us: int | None = None
        """Newest device time delivered (host ns in host mode)."""
        self.by_host_fallback = False
        self._channel = trigger_channel
        self._hold_ns = round(hold_s * 1e9)
        self._max_held = max_held
        self._clock_ns = clock_ns
        self._held: list[ItemT] = []
        self._held_since_ns: int | None = None
        self._d0: float | None = None  # device time of pulse 0
        self._ref: tuple[float, int] | None = None  # newest (device time, pulse index) pair
        self._rate = 1.0  # device us per box us, measured between paired edges
        self._host_off_ns: int | None = None  # host mode: min(arrival - newest device time) of packets

    # -- device-time bounds ----------------------------------------------------------------
    def _device_time(self, rel_us: int) -> float | None:
        """Device time of a box time relative to pulse 0."""
        if self._ref is None or self._d0 is None:
            return None
        d_ref, k_ref = self._ref
        return d_ref + (rel_us - self.window.offset_us(k_ref)) * self._rate

    @property
    def start_device_us(self) -> float | None:
        return None if self._d0 is None else self._d0 + self.window.start_rel_us * self._rate

    @property
    def end_device_us(self) -> float | None:
        """The window end in the device's clock (host ns in host mode); None while unknown."""
        if self.mode == "host":
            return self.window.host_bounds_ns()[1]
        end = self.window.end_rel_us
        return None if end is None else self._device_time(end)

    def _pair(self, t: NDArray[np.int64]) -> NDArray[np.int64]:
        """Pulse indices of device times of pulses (rising edges, exposures), in order."""
        if t.size == 0:
            return np.empty(0, np.int64)
        period = self.window.period_us * self._rate
        if self._ref is None:
            self._d0 = float(t[0])
            self._ref = (float(t[0]), 0)
        d_ref, k_ref = self._ref
        # Each one from its predecessor: drift only accumulates between consecutive pulses.
        steps = np.diff(np.concatenate(([d_ref], t.astype(np.float64))))
        k = k_ref + np.cumsum(np.maximum(np.rint(steps / period), 0)).astype(np.int64)
        self._ref = (float(t[-1]), int(k[-1]))
        if k[-1] > 0 and self._d0 is not None:
            span = self.window.offset_us(int(k[-1]))
            self._rate = (float(t[-1]) - self._d0) / span
        return k

    def note_stream_time(self, t_device_us: int) -> None:
        """The sensor's stream has got to this device time (its time words say so, events or
        not): a quiet sensor closes its window without waiting for an event past the end."""
        if self.mode == "trigger_in" and self._d0 is not None and not self._held:
            self._reached(int(t_device_us), self.end_device_us)

    # -- admitting ---------------------------------------------------------------------------
    def admit(self, item: ItemT) -> list[ItemT]:
        """The parts of `item` inside the window (held items come out once placeable)."""
        if self.mode != "host":
            return self._admit_timed(item)
        if self.window.first_pulse_us is None:
            return self._hold(item)
        return [part for held in self._release() for part in self._by_host(held)] + self._by_host(item)

    @abstractmethod
    def _admit_timed(self, item: ItemT) -> list[ItemT]:
        """Place `item` in the window by its device times (the gate's device-clock mode)."""

    @abstractmethod
    def _count(self, item: ItemT) -> tuple[int, int]:
        """(frames or events, trigger edges) in `item`: what is counted when it lies outside."""

    def _placed_by_device(self, item: ItemT) -> list[ItemT] | None:
        """Host mode: the item's part inside the window judged by its device times mapped to
        the host clock, where the kind can map them; None: judge it by its arrival."""
        return None

    def finish(self) -> list[ItemT]:
        """At the end of the take, what is still held: placed by host time when a pulse record
        came, else passed through (nothing to place it with)."""
        if not self._held:
            return []
        if self.window.first_pulse_us is not None:
            log.warning(
                "%s: no trigger edge came to place its window; %d held packets placed by host time",
                self.name,
                len(self._held),
            )
            self.by_host_fallback = self.mode != "host"
            self.mode = "host"
            return [part for held in self._release() for part in self._by_host(held)]
        log.warning(
            "%s: %d packets held for the window's start were never placed (no pulse record); "
            "written as they are",
            self.name,
            len(self._held),
        )
        return self._release()

    def _hold(self, item: ItemT) -> list[ItemT]:
        now = self._clock_ns()
        if self._held_since_ns is None:
            self._held_since_ns = now
        self._held.append(item)
        if now - self._held_since_ns <= self._hold_ns and len(self._held) < self._max_held:
            return []
        # Nothing to place the window with: from here by host time.
        self.by_host_fallback = self.mode != "host"
        if self.by_host_fallback:
            log.warning(
                "%s: no trigger edge within %.1f s (%d packets held); its take window is applied by "
                "host time from here",
                self.name,
                self._hold_ns / 1e9,
                len(self._held),
            )
            self.mode = "host"
        if self.window.first_pulse_us is None:
            log.warning("%s: no pulse record yet to place its data in the take window; passing it", self.name)
            return self._release()
        return [part for held in self._release() for part in self._by_host(held)]

    def _release(self) -> list[ItemT]:
        held, self._held, self._held_since_ns = self._held, [], None
        return held

    def _by_host(self, item: ItemT) -> list[ItemT]:
        if (placed := self._placed_by_device(item)) is not None:
            return placed
        host = item.host_time_ns
        h_start, h_end = self.window.host_bounds_ns()
        self._reached(host, h_end)
        n, n_trig = self._count(item)
        if h_start is not None and host < h_start:
            self.counts.before += n
            self.counts.triggers_before += n_trig
            return []
        if h_end is not None and host >= h_end:
            self.counts.after += n
            self.counts.triggers_after += n_trig
            return []
        return [item]

    def _reached(self, newest: int, end: float | None) -> None:
        if self.reached_us is None or newest > self.reached_us:
            self.reached_us = newest
        if end is not None and self.reached_us is not None and self.reached_us >= end:
            self.closed = True

    def reached_end(self) -> bool:
        """Whether nothing of the window is still to come from the device: its data got to the
        window end, or, for a camera triggered by the pulses, its frame of the take's last pulse
        came (its last frame is at that pulse, never past the window end; the last pulse may be
        fixed, by a stop, after that frame arrived)."""
        if self.closed:
            return True
        last, ref = self.window.last_index, self._ref
        if self.mode == "pulse_frames":
            return last is not None and ref is not None and ref[1] >= last
        end, reached = self.end_device_us, self.reached_us
        return end is not None and reached is not None and reached >= end

    def still_to_come(self) -> tuple[int | None, int | None]:
        """(reached, window end) of a gate not closed: the span it has not delivered."""
        end = self.end_device_us
        return self.reached_us, None if end is None else math.ceil(end)


class FrameGate(WindowGate[Frame]):
    """A camera's gate: `pulse_frames` (hardware-triggered with device timestamps: the first
    frame is pulse 0, later ones paired by their spacing) or `host`."""

    def _admit_timed(self, item: Frame) -> list[Frame]:
        k = int(self._pair(np.array([item.t_exposure_start_us], np.int64))[0])
        last = self.window.last_index
        self._reached(item.t_exposure_start_us, None)
        if last is not None and k >= last:
            self.closed = True
        if last is not None and k > last:
            self.counts.after += 1
            return []
        return [item]

    def _count(self, item: Frame) -> tuple[int, int]:
        return 1, 0


class EventGate(WindowGate[EventPacket]):
    """An event sensor's gate: `trigger_in` (its rising edges paired with the pulses, packets
    split at the window's device-time edges) or `host` (its events' device times mapped to the
    host clock by the earliest arrival)."""

    def _admit_timed(self, item: EventPacket) -> list[EventPacket]:
        if self._d0 is None:
            rising = item.triggers.rising(self._channel)
            if len(rising) == 0:
                return self._hold(item)
            self._pair(rising.t[:1])
            held = self._release()
            return [part for h in held for part in self._split_events(h)] + self._split_events(item)
        return self._split_events(item)

    def _count(self, item: EventPacket) -> tuple[int, int]:
        return item.n_events, len(item.triggers)

    def _placed_by_device(self, item: EventPacket) -> list[EventPacket] | None:
        mapped = self._arrival_bounds(item)
        return None if mapped is None else self._split_events(item, *mapped)

    def _split_events(
        self,
        packet: EventPacket,
        bounds: tuple[float, float | None] | None = None,
        host_off_ns: int | None = None,
    ) -> list[EventPacket]:
        """The packet's part inside the window: by its trigger edges' device bounds, or by
        `bounds` in device us (host mode, from the arrival estimate `host_off_ns`)."""
        triggers = packet.triggers
        if bounds is None:
            rising = triggers.rising(self._channel)
            if len(rising) and self._ref is not None:
                self._pair(rising.t[rising.t > self._ref[0]])
            start_dev, end = self.start_device_us, self.end_device_us
            assert start_dev is not None
            start: float = start_dev
        else:
            start, end = bounds
        lo_key = math.ceil(start)
        hi_key = None if end is None else math.ceil(end)
        tt = triggers.t
        keep = tt >= start
        if end is not None:
            keep &= tt < end
        if not keep.all():
            self.counts.triggers_before += int(np.count_nonzero(tt < start))
            self.counts.triggers_after += int(np.count_nonzero(~keep & (tt >= start)))
        span = packet.span
        newest = max(span.t_last if span.n else -(2**62), int(tt.max()) if len(tt) else -(2**62))
        if host_off_ns is None:
            self._reached(newest, end)
        else:
            self._reached(newest * 1000 + host_off_ns, self.window.host_bounds_ns()[1])
        n = span.n
        if packet.raw is not None:
            # EVT words cannot be split: a packet with events inside the window is stored whole,
            # and finalize counts its events outside the window by the final clock map
            # (`stored_before`/`_after`); the take's reader clips them. Its span tells where it
            # lies unless it reaches past both edges (then its events say, decoded here).
            if not n or span.t_last < lo_key:
                lo = hi = n
            elif hi_key is not None and span.t_first >= hi_key:
                lo = hi = 0
            elif span.t_first >= lo_key or hi_key is None or span.t_last < hi_key:
                lo, hi = 0, n  # its first or its last event is inside
            else:
                lo, hi = self._cut(packet.events.t, lo_key, hi_key)
            if hi > lo:
                return [packet if keep.all() else packet.with_triggers(triggers[keep])]
        else:
            lo, hi = self._cut(packet.events.t, lo_key, hi_key)
        self.counts.before += lo
        self.counts.after += n - hi
        if lo == 0 and hi == n and keep.all():
            return [packet]
        if hi == lo and not keep.any():
            return []
        return [EventPacket(packet.events[lo:hi], triggers[keep], packet.host_time_ns)]

    @staticmethod
    def _cut(t: NDArray[np.int64], lo_key: int, hi_key: int | None) -> tuple[int, int]:
        """[lo, hi): the events at or after lo_key and before hi_key (integer keys: a float one
        would make numpy convert the whole int64 column to compare)."""
        lo = int(np.searchsorted(t, lo_key, side="left"))
        hi = len(t) if hi_key is None else int(np.searchsorted(t, hi_key, side="left"))
        return lo, max(lo, hi)

    def _arrival_bounds(self, packet: EventPacket) -> tuple[tuple[float, float | None], int] | None:
        """Host mode, an event packet: the window in the sensor's clock, from the earliest any
        packet arrived after its newest event (the lower envelope of arrival - device time; a
        backlog only adds to it). So a packet read late, from a loaded host or a backlog, is
        judged by when its events happened, not by when it was read. None (judge by arrival)
        before a packet with events, or when this one maps further back than any backlog can
        (a device clock that jumped back)."""
        if not packet.n_events:
            return None
        h_start, h_end = self.window.host_bounds_ns()
        if h_start is None:
            return None
        arrival = packet.host_time_ns - packet.span.t_last * 1000
        if self._host_off_ns is None or arrival < self._host_off_ns:
            self._host_off_ns = arrival
        off = self._host_off_ns
        if arrival - off > MAX_MAPPED_LAG_NS:
            return None
        return ((h_start - off) / 1000, None if h_end is None else (h_end - off) / 1000), off
