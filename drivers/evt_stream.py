"""An event sensor that delivers an EVT byte stream, decoded on the host.

This is how a Prophesee camera talks (OpenEB's HAL hands out raw EVT buffers), how a RAW file
replays, and how the simulated sensor talks: all three are `ByteSource`s behind one
`EvtStreamSensor`, so the decoder the tests exercise is the one the rig runs.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Protocol

from drivers.base import AcquisitionStats, Capability, EventPacket, EventSensor
from drivers.evt import StreamDecoder
from rigd.core.devices import DeviceInfo
from rigd.core.errors import DeviceError
from rigd.core.settings import EventSensorSettings

log = logging.getLogger(__name__)


class ByteSource(Protocol):
    """The device side of a streaming event sensor."""

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

    def stats(self) -> AcquisitionStats:
        """Device-side counters (buffers lost in the device or transport)."""
        ...


class EvtStreamSensor(EventSensor):
    """Decodes a `ByteSource` into event packets; decoder skips are counted, never silent."""

    def __init__(self, source: ByteSource, *, strict: bool = False) -> None:
        self.source = source
        width, height = source.geometry
        self._decoder = StreamDecoder(source.evt_format, width=width, height=height, strict=strict)
        self._lock = threading.Lock()
        self._delivered = 0
        self._bytes = 0
        self._closed = False

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

    def configure(self, settings: EventSensorSettings) -> None:
        self._check_open()
        self.source.configure(settings)

    def start(self) -> None:
        self._check_open()
        self.source.start()

    def stop(self) -> None:
        self.source.stop()

    def close(self) -> None:
        if self._closed:
            return
        try:
            self.source.close()
        finally:
            self._closed = True
            skipped = {k: v for k, v in self._decoder.stats.items() if v}
            if skipped:
                log.warning("%s: decoder skipped %s", self.info.spec, skipped)

    def read_events(self, timeout_s: float) -> EventPacket | None:
        self._check_open()
        deadline = time.monotonic() + max(timeout_s, 0.0)
        while True:
            got = self.source.read_bytes(max(0.0, deadline - time.monotonic()))
            if got is None:
                return None
            data, host_ns = got
            decoded = self._decoder.feed(data)
            with self._lock:
                self._bytes += len(data)
                self._delivered += len(decoded.events)
            if len(decoded.events) or len(decoded.triggers):
                return EventPacket(decoded.events, decoded.triggers, host_ns)
            if time.monotonic() >= deadline:
                return None

    def stats(self) -> AcquisitionStats:
        dev = self.source.stats()
        extra = dict(dev.extra)
        extra["bytes_decoded"] = self._bytes
        for kind, n in self._decoder.stats.items():
            extra[f"decoder_skipped_{kind}"] = n
        with self._lock:
            return AcquisitionStats(delivered=self._delivered, device_dropped=dev.device_dropped, extra=extra)

    def _check_open(self) -> None:
        if self._closed:
            raise DeviceError(f"event sensor {self.info.spec} is closed")
