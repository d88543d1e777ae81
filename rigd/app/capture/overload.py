"""Overload: what the capture does when data arrives faster than the host can write it.

A Prophesee sensor that produces more than its link or buffer takes does not stall: its
event-rate controller (ERC) drops whole time slices and says so. The capture does the same at
its own source end. Each event sensor's channel asks its `SliceShedder` before handing a packet
to the writer; while the writer's queue is above its high-water mark (items or bytes), or the
packet already waited longer than `max_lag_s` since it reached the host, the packet's events
are shed (its trigger edges still go through: the sync engine needs every one) and the shed
span is written down as a loss record with its device-time range. Memory stays bounded by the
queue's budget, the lag by `max_lag_s`, and the take never ends in a backlog that has to be
left unread. Cameras are not shed here: a frame is one pulse of the sync, and the queue's own
bound (a put that times out is a counted loss) applies to them as before.

`WriterLoad` measures how busy the writer thread is, the live headroom the operator sees.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, Protocol, TypeVar

from rigd.app.capture.faults import FaultBoard
from rigd.app.capture.ledger import LossLedger
from rigd.core.events import EventArray, EventPacket, EventSpan
from rigd.core.frames import Frame

log = logging.getLogger(__name__)

SHED_REASON = (
    "shed at the source: the host could not keep up (overload); whole time slices were dropped, "
    "as a sensor's event-rate controller does; the count is exact, the range in device us"
)
#: A shed span stays open (one loss record) until admission has gone on this long.
SPAN_CLOSE_S = 0.5
#: Window of the writer's busy fraction (s).
LOAD_WINDOW_S = 2.0


ItemT = TypeVar("ItemT", Frame, EventPacket)


@dataclass(frozen=True, slots=True)
class Fill:
    """How full the writer queue is, as fractions of its bounds."""

    items: float
    bytes: float

    @property
    def worst(self) -> float:
        return max(self.items, self.bytes)


@dataclass(slots=True)
class _Span:
    count: int
    t_first: int | None
    t_last: int | None
    packets: int
    last_shed_mono: float


class Shedding(Protocol[ItemT]):
    """A channel's load-shedding part: what of an item goes to the writer while it falls behind."""

    shed_events: int

    def admit(self, item: ItemT, fill: Fill, now_ns: int) -> ItemT | None: ...
    def close(self) -> None: ...


class KeepAll(Generic[ItemT]):
    """No shedding: every item goes to the queue, whose bound counts what it cannot take
    (cameras: a frame is one item, there is no slice of it to shed)."""

    shed_events = 0

    def admit(self, item: ItemT, fill: Fill, now_ns: int) -> ItemT | None:
        return item

    def close(self) -> None:
        return None


class SliceShedder:
    """One event sensor's overload gate (its acquisition thread alone calls `admit`).

    Hysteresis: shedding starts at `high` (fraction of the queue's bound) and stops at `low`,
    so the writer gets whole runs of packets and the stream is cut in few places.
    """

    def __init__(
        self,
        device: str,
        ledger: LossLedger,
        faults: FaultBoard,
        *,
        high: float = 0.75,
        low: float = 0.5,
        max_lag_s: float = 1.0,
        clock: Callable[[], float] | None = None,
    ) -> None:
        if not 0 < low < high <= 1:
            raise ValueError(f"shedding needs 0 < low < high <= 1, got low={low} high={high}")
        self.device = device
        self._ledger = ledger
        self._faults = faults
        self._high, self._low, self._max_lag_ns = high, low, int(max_lag_s * 1e9)
        self._clock = clock or time.monotonic
        self._shedding = False
        self._span: _Span | None = None
        self.shed_events = 0
        """Events shed so far (all spans)."""
        self.spans = 0
        """Loss records written (closed spans)."""

    @property
    def shedding(self) -> bool:
        return self._shedding

    def admit(self, packet: EventPacket, fill: Fill, now_ns: int) -> EventPacket | None:
        """The packet to hand to the writer (itself, or its trigger edges alone while shedding),
        or None when nothing of it is left to write."""
        lagging = now_ns - packet.host_time_ns > self._max_lag_ns
        if self._shedding:
            self._shedding = fill.worst > self._low or lagging
        else:
            self._shedding = fill.worst >= self._high or lagging
        now = self._clock()
        if not self._shedding:
            span = self._span
            if span is not None and now - span.last_shed_mono >= SPAN_CLOSE_S:
                self._close()
            return packet
        self._shed(packet.span, now)
        if len(packet.triggers) == 0:
            return None
        return EventPacket(EventArray.empty(), packet.triggers, packet.host_time_ns)

    def _shed(self, events: EventSpan, now: float) -> None:
        n = events.n
        span = self._span
        if span is None:
            span = self._span = _Span(0, None, None, 0, now)
            self._faults.set(
                "overload",
                self.device,
                f"{self.device}: the host cannot keep up; event slices are shed (counted)",
            )
            log.warning("%s: overload, shedding event slices", self.device)
        span.packets += 1
        span.last_shed_mono = now
        if n:
            span.count += n
            if span.t_first is None:
                span.t_first = events.t_first
            span.t_last = events.t_last
        self.shed_events += n

    def _close(self) -> None:
        span, self._span = self._span, None
        if span is None:
            return
        self.spans += 1
        self._ledger.add(
            self.device,
            "events",
            span.count,
            f"{SHED_REASON} ({span.packets} packet(s))",
            (span.t_first, span.t_last),
        )
        self._faults.clear("overload", self.device)
        log.warning("%s: shed %d events in %d packet(s)", self.device, span.count, span.packets)

    def close(self) -> None:
        """End of the take: an open span becomes its loss record."""
        self._close()


class WriterLoad:
    """The writer thread's busy fraction over the last `LOAD_WINDOW_S` (thread-safe reads)."""

    def __init__(self, clock: Callable[[], float] | None = None) -> None:
        self._clock = clock or time.monotonic
        self._lock = threading.Lock()
        self._busy: deque[tuple[float, float]] = deque()
        self._busy_total = 0.0
        self.busy_s = 0.0
        """Busy seconds since the start."""
        self._t0 = self._clock()

    def add(self, start: float, end: float) -> None:
        with self._lock:
            self._busy.append((end, end - start))
            self._busy_total += end - start
            self.busy_s += end - start
            self._trim(end)

    def _trim(self, now: float) -> None:
        while self._busy and now - self._busy[0][0] > LOAD_WINDOW_S:
            self._busy_total -= self._busy.popleft()[1]

    def fraction(self) -> float:
        """Busy share of the last window (0..1)."""
        now = self._clock()
        with self._lock:
            self._trim(now)
            span = min(LOAD_WINDOW_S, max(now - self._t0, 1e-3))
            return min(1.0, max(0.0, self._busy_total / span))
