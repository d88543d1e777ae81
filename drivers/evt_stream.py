"""An event sensor that delivers an EVT byte stream, decoded on the host.

This is how a Prophesee camera talks (OpenEB's HAL hands out raw EVT buffers) and how the
simulated and the replayed sensors talk: each is a `DecodingEventSensor`, so the decoder the
tests exercise is the one the rig runs. The base class's acquisition thread polls the device
(`_grab`: one buffer of EVT words and the host time it arrived) into the bounded queue whose
overflow is counted; a read takes up to `merge` queued buffers, joins them and scans their
words into one `EventPacket`, on the reader's thread. Lifecycle, the queue, error hand-over
and the delivered count are the base class's (`drivers.base.AcquiringDevice`, decision 0010).

A `file://` recording is not a device to poll: `drivers.file_event_sensor` cuts its stream by
due time on the reader's thread, with a decoder of its own.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Generic

from typing_extensions import TypeVar

from drivers.base import EventSensor
from rigd.core.events import EventPacket, EvtChunk
from rigd.core.settings import EventSensorSettings
from rigd.evt import StreamDecoder, warm_up_decoder

log = logging.getLogger(__name__)

#: Bytes of time words (no event, no edge) carried into the next packet's chunk at most; past
#: that they are let go (they decode to nothing) and the next chunk starts from its own state.
_MAX_QUIET_BYTES = 1 << 20


@dataclass(frozen=True, slots=True)
class EvtBuffer:
    """One device buffer: EVT words as the device sent them, and the host monotonic time (ns)
    they arrived."""

    data: bytes
    host_ns: int


B = TypeVar("B", bound=EvtBuffer, default=EvtBuffer)


class DecodingEventSensor(EventSensor[B], Generic[B]):
    """An event sensor whose acquisition thread grabs EVT buffers that its reads decode.

    Subclasses set `_info` and `_capabilities`, pass the stream's format and geometry, and
    implement `_grab` (a `B`, None when nothing came, END when nothing more will) with the
    lifecycle hooks their device needs; `_join` may check or note what a read takes before
    calling this one. Subclasses that override `_counters`, `_do_close` or `warm_up` include
    this class's (decoder counters, its skips logged at close, its kernels compiled).

    Decoder skips are counted, never silent. Every packet carries the words it was decoded
    from (`EventPacket.raw`); the words of a valid stream are only scanned
    (`StreamDecoder.scan`), their events decoded when asked for.
    """

    delivers_evt_words = True

    def __init__(
        self,
        fmt: str,
        geometry: tuple[int, int],
        *,
        buffers: int,
        merge: int = 1,
        drain_on_stop: bool = False,
        strict: bool = False,
    ) -> None:
        super().__init__(EventSensorSettings(), queue_len=buffers, drain_on_stop=drain_on_stop)
        self._fmt = fmt
        self._geometry = geometry
        self._merge = merge
        self._decoder = StreamDecoder(fmt, width=geometry[0], height=geometry[1], strict=strict)
        self._bytes = 0
        self._quiet: EvtChunk | None = None
        """Decoded bytes that gave nothing yet, so the next packet's chunk carries them."""

    @property
    def geometry(self) -> tuple[int, int]:
        return self._geometry

    @property
    def evt_format(self) -> str:
        """One of rigd.evt.FORMATS: the encoding of the buffers `_grab` returns."""
        return self._fmt

    @property
    def stream_time_us(self) -> int | None:
        """How far the decoded stream has got, its time words included (EVT 3.0)."""
        return self._decoder.time_us

    def warm_up(self) -> None:
        """This stream's decoder, compiled on a sample of its format."""
        warm_up_decoder(self._fmt, *self._geometry)

    def _do_close(self) -> None:
        skipped = {k: v for k, v in self._decoder.stats.items() if v}
        if skipped:
            log.warning("%s: decoder skipped %s", self.label, skipped)
        if self._decoder.time_jumps:
            log.warning("%s: stream time jumped back %d time(s)", self.label, self._decoder.time_jumps)

    def _join(self, items: list[B]) -> tuple[bytes, int]:
        """Reader's thread: the buffers in order as one, stamped when the last arrived (its
        newest events)."""
        if len(items) == 1:
            return items[0].data, items[0].host_ns
        return b"".join(b.data for b in items), items[-1].host_ns

    def _read(self, timeout_s: float) -> EventPacket | None:
        """Up to `merge` buffers as one packet; buffers of time words alone are carried into the
        next packet's chunk, and reading goes on until the timeout."""
        deadline = time.monotonic() + max(timeout_s, 0.0)
        first = True
        while True:
            if not first:
                self._check_present()
            first = False
            items = self._read_queued(max(0.0, deadline - time.monotonic()), self._merge)
            if not items:
                return self._flushed()
            data, host_ns = self._join(items)
            scanned, chunk = self._decoder.scan_chunk(data)
            self._bytes += len(data)
            chunk = self._joined(chunk)
            if not scanned.empty:
                return scanned.packet(host_ns, chunk)
            self._keep_quiet(chunk)
            if time.monotonic() >= deadline:
                return None

    def _joined(self, chunk: EvtChunk) -> EvtChunk:
        """The chunk with the quiet bytes decoded before it in front (one copy, rare)."""
        quiet, self._quiet = self._quiet, None
        if quiet is None or not chunk.continues(quiet):
            return chunk
        data = quiet.data + chunk.data
        return EvtChunk(chunk.fmt, data, quiet.state, quiet.stream, quiet.offset, geometry=chunk.geometry)

    def _keep_quiet(self, chunk: EvtChunk) -> None:
        if chunk.data and len(chunk.data) <= _MAX_QUIET_BYTES:
            self._quiet = chunk

    def _flushed(self) -> EventPacket | None:
        """Once stopped and drained: what the decoder held back at a time jump it could not yet
        confirm, decided now (no more bytes will tell), so nothing stays behind unreported."""
        if self.acquiring or not self._decoder.holding:
            return None
        decoded, chunk = self._decoder.flush_chunk()
        if len(decoded.events) or len(decoded.triggers):
            raw = None if chunk is None else self._joined(chunk)
            return EventPacket(decoded.events, decoded.triggers, self.host_clock.now_ns(), raw)
        return None

    def _counters(self) -> tuple[int, dict[str, int]]:
        """The decoder's counters (subclasses put their device's in front)."""
        extra = {"bytes_decoded": self._bytes}
        for kind, n in self._decoder.stats.items():
            extra[f"decoder_skipped_{kind}"] = n
        extra.update({f"decoder_{k}": v for k, v in self._decoder.jump_stats.items()})
        return 0, extra
