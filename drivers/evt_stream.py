"""An event sensor that delivers an EVT byte stream, decoded on the host.

This is how a Prophesee camera talks (OpenEB's HAL hands out raw EVT buffers) and how the
simulated sensor talks: both are `ByteSource`s behind one `EvtStreamSensor`, so the decoder
the tests exercise is the one the rig runs. Sources that must be polled (the HAL, the
simulated firmware) derive from `GrabbingSource`, which runs the poll on an acquisition
thread into a bounded buffer whose overflow is counted.
"""

from __future__ import annotations

import abc
import logging
import time
from typing import Generic, Protocol, TypeVar

from drivers.base import AcquisitionStats, Capability, EventSensor
from drivers.evt import StreamDecoder, warm_up_decoder
from drivers.lifecycle import Acquisition, DeliveryQueue, Signal
from rigd.core.devices import DeviceInfo
from rigd.core.events import EventPacket, EvtChunk
from rigd.core.settings import EventSensorSettings

log = logging.getLogger(__name__)

T = TypeVar("T")
#: Bytes of time words (no event, no edge) carried into the next packet's chunk at most; past
#: that they are let go (they decode to nothing) and the next chunk starts from its own state.
_MAX_QUIET_BYTES = 1 << 20


class ByteSource(Protocol):
    """The device side of a streaming event sensor. `EvtStreamSensor` enforces the lifecycle:
    a source sees configure only while stopped, start/stop in pairs, and close once."""

    @property
    def info(self) -> DeviceInfo: ...

    @property
    def capabilities(self) -> frozenset[Capability]: ...

    @property
    def geometry(self) -> tuple[int, int]: ...

    @property
    def evt_format(self) -> str:
        """One of drivers.evt.FORMATS: the encoding of the bytes `read_bytes` returns."""
        ...

    def configure(self, settings: EventSensorSettings) -> None: ...

    def start(self) -> None: ...

    def stop(self) -> None: ...

    def close(self) -> None: ...

    def read_bytes(self, timeout_s: float) -> tuple[bytes, int] | None:
        """Next buffer and the host monotonic time (ns) it arrived, or None on timeout."""
        ...

    def warm_up(self) -> None:
        """Compile what making the bytes runs (a simulator's kernels); see `Device.warm_up`."""
        ...

    def stats(self) -> AcquisitionStats:
        """Device-side counters (what was lost in the device or transport)."""
        ...


class GrabbingSource(abc.ABC, Generic[T]):
    """A `ByteSource` whose device is polled by `_grab` on an acquisition thread; up to
    `buffers` items wait for `read_bytes`, which joins up to `merge` of them into one buffer.

    Subclasses set `_info`, `_capabilities`, `_geometry` and `_fmt`, and implement `_grab`,
    `_join` and `stats`; `_do_start` / `_do_stop` / `_do_close` as their device needs.
    """

    _info: DeviceInfo
    _capabilities: frozenset[Capability]
    _geometry: tuple[int, int]
    _fmt: str

    def __init__(self, label: str, *, buffers: int, merge: int = 1, drain_on_stop: bool = False) -> None:
        self._merge = merge
        self._acq: Acquisition[T] = Acquisition(
            label, self._grab, DeliveryQueue(buffers), deliver=self._deliver, drain_on_stop=drain_on_stop
        )

    @property
    def info(self) -> DeviceInfo:
        return self._info

    @property
    def capabilities(self) -> frozenset[Capability]:
        return self._capabilities

    @property
    def geometry(self) -> tuple[int, int]:
        return self._geometry

    @property
    def evt_format(self) -> str:
        return self._fmt

    def start(self) -> None:
        self._check_present()
        self._do_start()
        self._acq.start()

    def stop(self) -> None:
        try:
            self._do_stop()
        finally:
            self._acq.stop()

    def close(self) -> None:
        self._do_close()

    def warm_up(self) -> None:
        """Nothing to compile by default (a camera's firmware makes its bytes)."""

    def read_bytes(self, timeout_s: float) -> tuple[bytes, int] | None:
        self._check_present()
        items = self._acq.read(timeout_s, max_items=self._merge)
        return self._join(items) if items else None

    # -- hooks -----------------------------------------------------------------------------
    def _check_present(self) -> None:
        """Raise DeviceError when the device is gone (unplugged)."""

    def _do_start(self) -> None: ...

    def _do_stop(self) -> None: ...

    def _do_close(self) -> None: ...

    @abc.abstractmethod
    def _grab(self, timeout_s: float) -> T | Signal | None:
        """Acquisition thread: next item, None when none came, END when nothing more will."""

    def _deliver(self, item: T) -> bool:
        """Acquisition thread: buffer an item; False when the full buffer lost one (counted)."""
        lost = self._acq.queue.put(item)
        if lost is None:
            return True
        self._on_overflow(lost)
        return False

    def _on_overflow(self, lost: T) -> None:
        log.warning("%s: host buffer full, a buffer was lost", self._acq.label)

    @abc.abstractmethod
    def _join(self, items: list[T]) -> tuple[bytes, int]:
        """Reader's thread: one byte buffer and its host time (ns) from up to `merge` items."""


class EvtStreamSensor(EventSensor):
    """Decodes a `ByteSource` into event packets; decoder skips are counted, never silent.
    Every packet carries the words it was decoded from (`EventPacket.raw`); the words of a
    valid stream are only scanned (`StreamDecoder.scan`), their events decoded when asked for."""

    delivers_evt_words = True

    def __init__(self, source: ByteSource, *, strict: bool = False) -> None:
        super().__init__(EventSensorSettings())
        self.source = source
        width, height = source.geometry
        self._decoder = StreamDecoder(source.evt_format, width=width, height=height, strict=strict)
        self._bytes = 0
        self._quiet: EvtChunk | None = None
        """Decoded bytes that gave nothing yet, so the next packet's chunk carries them."""

    @property
    def info(self) -> DeviceInfo:
        return self.source.info

    @property
    def capabilities(self) -> frozenset[Capability]:
        return self.source.capabilities

    @property
    def geometry(self) -> tuple[int, int]:
        return self.source.geometry

    @property
    def evt_format(self) -> str:
        return self.source.evt_format

    @property
    def stream_time_us(self) -> int | None:
        """How far the decoded stream has got, its time words included (EVT 3.0)."""
        return self._decoder.time_us

    def warm_up(self) -> None:
        """The source's kernels, then this stream's decoder (on a sample of its format)."""
        self.source.warm_up()
        warm_up_decoder(self.source.evt_format, *self.source.geometry)

    def _do_configure(self, settings: EventSensorSettings) -> None:
        self.source.configure(settings)

    def _do_start(self) -> None:
        self.source.start()

    def _do_stop(self) -> None:
        self.source.stop()

    def _do_close(self) -> None:
        self.source.close()
        skipped = {k: v for k, v in self._decoder.stats.items() if v}
        if skipped:
            log.warning("%s: decoder skipped %s", self.label, skipped)
        if self._decoder.time_jumps:
            log.warning("%s: stream time jumped back %d time(s)", self.label, self._decoder.time_jumps)

    def _read(self, timeout_s: float) -> EventPacket | None:
        deadline = time.monotonic() + max(timeout_s, 0.0)
        while True:
            got = self.source.read_bytes(max(0.0, deadline - time.monotonic()))
            if got is None:
                return self._flushed()
            data, host_ns = got
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
            return EventPacket(decoded.events, decoded.triggers, time.monotonic_ns(), raw)
        return None

    def _counters(self) -> tuple[int, dict[str, int]]:
        dev = self.source.stats()
        extra = dict(dev.extra)
        extra["bytes_decoded"] = self._bytes
        for kind, n in self._decoder.stats.items():
            extra[f"decoder_skipped_{kind}"] = n
        extra.update({f"decoder_{k}": v for k, v in self._decoder.jump_stats.items()})
        return dev.device_dropped, extra
