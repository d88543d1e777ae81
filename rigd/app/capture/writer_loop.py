"""The writer thread: takes items off the queue, writes them, flushes the take periodically.

It alone touches the take file while the take runs, and records in each device's stream what
reached it (`streams`: no call back into the channels). Bad data from one device is refused
and counted without costing the rest; a file system that refuses a write (disk full, I/O
error) stops the take cleanly: everything flushed before stays, what comes after is counted.
"""

from __future__ import annotations

import errno
import logging
import time
from collections.abc import Mapping
from typing import Any

from rigd.app.capture.ballast import Ballast
from rigd.app.capture.control import RunControl, utc_now
from rigd.app.capture.faults import FaultBoard
from rigd.app.capture.items import QueueItem, Stop, WriterQueue
from rigd.app.capture.ledger import LossLedger
from rigd.app.capture.overload import WriterLoad
from rigd.app.capture.streams import Stream
from rigd.core.errors import TakeError, WriteDeferredError
from rigd.core.fault_codes import FaultCode
from rigd.take.writer import TakeWriter

log = logging.getLogger(__name__)


class WriterLoop:
    def __init__(
        self,
        writer: TakeWriter,
        queue: WriterQueue,
        streams: Mapping[str, Stream[Any]],
        ledger: LossLedger,
        faults: FaultBoard,
        control: RunControl,
        ballast: Ballast | None,
        flush_interval_s: float,
        *,
        relieve_at: float = 0.0,
    ) -> None:
        self.writer = writer
        self._queue = queue
        self._streams = streams
        """Each device's stream by the name its items carry (the box's: "trigger")."""
        self._ledger = ledger
        self._faults = faults
        self._control = control
        self._ballast = ballast
        self._interval = flush_interval_s
        self._relieve_at = relieve_at
        self.relieved = 0
        """Times the writer fell behind and stored EVT words uncompressed until it caught up."""
        self._relieving = False
        self.error: OSError | None = None
        """What the file system refused; the take stopped there."""
        self.last_flush_utc: str | None = None
        self.last_flush_mono: float | None = None
        self.load = WriterLoad()
        """How busy this thread is (the headroom telemetry shows)."""

    def run(self) -> None:
        """The thread body: until the stop item, then a last flush."""
        last_flush = time.monotonic()
        while True:
            item = self._queue.get(min(0.2, self._interval / 2))
            if item is Stop.STOP:
                if self.error is None:
                    self._flush()
                self._note_relief()
                return
            if item is not None:
                t0 = time.monotonic()
                if self._relieve_at:
                    self._relieve()
                self._take(item)
                self.load.add(t0, time.monotonic())
            now = time.monotonic()
            if self.error is None and now - last_flush >= self._interval:
                try:
                    self._flush()
                except OSError as exc:
                    self._failed(exc)
                self.load.add(now, time.monotonic())
                last_flush = now

    def _relieve(self) -> None:
        """Behind (the queue past `relieve_at`): EVT words go to the file uncompressed, so the
        writer catches up on disk bytes instead of the sensors shedding events; back to
        compressing once the queue is under half of that."""
        fill = self._queue.fill().worst
        if not self._relieving and fill >= self._relieve_at:
            self._relieving = True
            self.relieved += 1
            self.writer.compress_events(False)
            log.warning(
                "writer behind (queue %.0f %% full): EVT words stored uncompressed until it catches up",
                100 * fill,
            )
        elif self._relieving and fill <= self._relieve_at / 2:
            self._relieving = False
            self.writer.compress_events(True)
            log.info("writer caught up: EVT words compressed again")

    def _note_relief(self) -> None:
        """At the end: how much the writer stored uncompressed while it was behind."""
        if not self.relieved:
            return
        parts = [
            f"{name} {st.uncompressed_chunks} chunk(s)"
            for name, st in self.writer.stats.items()
            if st.uncompressed_chunks
        ]
        log.warning(
            "the writer fell behind %d time(s) and stored EVT words uncompressed meanwhile (%s): "
            "the take is complete, only larger; the host is near its capacity",
            self.relieved,
            ", ".join(parts) or "no whole chunk",
        )

    def _take(self, item: QueueItem) -> None:
        stream = self._streams[item.device]
        stream.live.dequeued()
        if self.error is not None:
            self._refused(item, f"not written: the take stopped ({self.error})")
            return
        try:
            stream.write(self.writer, item)
        except TakeError as exc:
            # Bad data from one device must not cost the rest of the take.
            log.error("refused data from %s: %s", item.device, exc)
            self._refused(item, str(exc))
            return
        except WriteDeferredError as exc:
            self._failed(exc)  # the take holds the item and writes it when it is failed
        except OSError as exc:
            self._failed(exc)
            self._refused(item, f"not written: {exc}")
            return
        stream.landed(item)

    def _flush(self) -> None:
        self.writer.flush(journal=self._ledger.journal())
        self.last_flush_utc = utc_now()
        self.last_flush_mono = time.monotonic()

    def _refused(self, item: QueueItem, reason: str) -> None:
        self._ledger.add(item.device, item.what, item.count, reason)

    def _failed(self, exc: OSError) -> None:
        """The file system refused a write (disk full, I/O error): stop the take cleanly."""
        self.error = exc
        if self._ballast is not None:
            self._ballast.release(emergency=True)  # room to close the take cleanly
        full = exc.errno == errno.ENOSPC or "No space left" in str(exc)
        code: FaultCode = "disk_full" if full else "writer_failed"
        self._faults.set(code, None, f"writing {self.writer.path.name} failed: {exc}")
        self._control.request_stop(f"{'disk full' if full else 'write error'}: {exc}", fault=True)
