"""What travels from the acquisition threads to the writer thread, and the queue between them.

The queue is bounded: a full queue blocks an acquisition thread for
`writer.queue_put_timeout_s`, after which the item is counted as lost with its time range,
never dropped silently.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass
from enum import Enum
from typing import ClassVar

from rigd.app.capture.faults import FaultBoard
from rigd.app.capture.ledger import LossLedger
from rigd.app.capture.live import LiveStats
from rigd.app.capture.overload import Fill
from rigd.core.devices import PulseBatch
from rigd.core.events import EventPacket
from rigd.core.frames import Frame
from rigd.core.schema import LossKind

log = logging.getLogger(__name__)

#: Bytes of one decoded event in memory (x, y: u2; p: i1; t: i8).
EVENT_BYTES = 13


@dataclass(frozen=True, slots=True)
class FrameItem:
    device: str
    frame: Frame
    what: ClassVar[LossKind] = "frames"

    @property
    def count(self) -> int:
        return 1

    @property
    def nbytes(self) -> int:
        return int(self.frame.image.nbytes)

    @property
    def t_range(self) -> tuple[int | None, int | None]:
        t = self.frame.t_exposure_start_us
        return (t, t)


@dataclass(frozen=True, slots=True)
class EventsItem:
    device: str
    packet: EventPacket
    what: ClassVar[LossKind] = "events"

    @property
    def count(self) -> int:
        return self.packet.n_events

    @property
    def nbytes(self) -> int:
        """Memory the item holds: decoded events (none when only scanned) and edges, and the
        wire bytes when kept (the same however often it is asked: the queue adds and takes it)."""
        p = self.packet
        raw = 0 if p.raw is None else len(p.raw.data)
        return (0 if p.from_scan else EVENT_BYTES * p.n_events) + 10 * len(p.triggers) + raw

    @property
    def t_range(self) -> tuple[int | None, int | None]:
        span = self.packet.span
        return (span.t_first, span.t_last) if span.n else (None, None)


@dataclass(frozen=True, slots=True)
class PulsesItem:
    batch: PulseBatch
    device: ClassVar[str] = "trigger"
    what: ClassVar[LossKind] = "pulses"

    @property
    def count(self) -> int:
        return len(self.batch)

    @property
    def nbytes(self) -> int:
        return 24 * len(self.batch)

    @property
    def t_range(self) -> tuple[int | None, int | None]:
        return (None, None)


class Stop(Enum):
    """The last item: the writer flushes and ends."""

    STOP = "stop"


QueueItem = FrameItem | EventsItem | PulsesItem


class WriterQueue:
    """The bounded hand-off to the writer; a put that times out is a counted loss.

    Bounded in items and, loosely, in bytes: a put waits while the bytes queued exceed
    `max_bytes` too (one item may overshoot), so a backlog of big frames cannot take the
    host's memory. `fill()` is what the event sensors' overload gates watch."""

    def __init__(
        self,
        maxsize: int,
        put_timeout_s: float,
        ledger: LossLedger,
        faults: FaultBoard,
        max_bytes: int = 1 << 62,
    ) -> None:
        self._queue: queue.Queue[QueueItem | Stop] = queue.Queue(maxsize=maxsize)
        self.maxsize = maxsize
        self.max_bytes = max_bytes
        self._put_timeout_s = put_timeout_s
        self._ledger = ledger
        self._faults = faults
        self._bytes = 0
        self.peak_bytes = 0
        self._room = threading.Condition()

    @property
    def bytes_queued(self) -> int:
        return self._bytes

    def fill(self) -> Fill:
        return Fill(self._queue.qsize() / self.maxsize, self._bytes / self.max_bytes)

    def _wait_for_bytes(self, timeout_s: float) -> bool:
        with self._room:
            return self._room.wait_for(lambda: self._bytes < self.max_bytes, timeout_s)

    def put(self, item: QueueItem, live: LiveStats) -> bool:
        live.enqueued()
        t0 = time.monotonic()
        try:
            if not self._wait_for_bytes(self._put_timeout_s):
                raise queue.Full
            left = max(0.0, self._put_timeout_s - (time.monotonic() - t0))
            with self._room:
                self._bytes += item.nbytes
                self.peak_bytes = max(self.peak_bytes, self._bytes)
            try:
                self._queue.put(item, timeout=left)
            except queue.Full:
                self._release(item)
                raise
        except queue.Full:
            log.warning("writer queue full: %d %s of %s lost", item.count, item.what, item.device)
            self._faults.set("queue_full", None, "the writer cannot keep up; data is being dropped (counted)")
            live.dequeued()
            self._ledger.add(
                item.device, item.what, item.count, "writer queue full (host could not keep up)", item.t_range
            )
            return False
        if self._faults.is_active("queue_full", None) and self._queue.qsize() < self.maxsize // 2:
            self._faults.clear("queue_full", None)  # the writer caught up
        return True

    def put_stop(self) -> None:
        self._queue.put(Stop.STOP)

    def get(self, timeout_s: float) -> QueueItem | Stop | None:
        try:
            item = self._queue.get(timeout=timeout_s)
        except queue.Empty:
            return None
        if item is not Stop.STOP:
            self._release(item)
        return item

    def _release(self, item: QueueItem) -> None:
        with self._room:
            self._bytes -= item.nbytes
            self._room.notify_all()

    def qsize(self) -> int:
        return self._queue.qsize()
