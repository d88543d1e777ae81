"""Per-device sinks: what the writer buffers for one device and how it lands in the file.

Small per-item series (frame times, triggers, pulses) are buffered and written in blocks, so
HDF5 is not called per item; events are written in whole chunks while recording, the rest of a
flush going to the sensor's tail slots (`rigd.take.tails`). Columns of one group are written
in a fixed order with `t` last, so a kill between two column writes leaves `t` no longer than
the others and `check_repair` can cut the group back to what every column holds.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Self

import h5py
import numpy as np
from numpy.typing import DTypeLike, NDArray

from rigd.core.devices import PulseBatch
from rigd.core.errors import TakeError, TakeFormatError
from rigd.core.events import EventArray, EventPacket, TriggerEvents
from rigd.core.frames import Frame
from rigd.core.layout import (
    EVENT_DTYPES,
    EVENTS_GROUP,
    FRAME_SERIES,
    FRAMES_GROUP,
    PULSE_SERIES,
    TRIGGER_DTYPES,
    Device,
    Events,
    Frames,
    Pulses,
    TriggerEdges,
)
from rigd.core.pixels import BAYER_PATTERNS, PIXEL_FORMATS, is_bayer, stored_pixel_format
from rigd.take.h5file import append_rows, require_dataset, require_group, write_chunk
from rigd.take.tails import choose_tail_slot, create_tail_slots, drop_tail_slots
from rigd.take.units import label

if TYPE_CHECKING:
    from rigd.core.timebase import ClockMap
    from rigd.take.finalize import Finalizer

#: Frames are allocated in blocks of this many, so the images dataset is not resized per frame.
_FRAME_BLOCK = 64
#: Small per-item buffers (frame timestamps, triggers, pulses) are written when this full.
_SMALL_BLOCK = 4096
#: Chunk length of small 1-D datasets (frame times, triggers, pulses, ms_to_idx).
SMALL_CHUNK = 4096
#: Buffered events are written (as whole chunks) once this many are held, so small chunks do
#: not cost one resize and four HDF5 writes each.
EVENT_WRITE_BLOCK = 1 << 18


@dataclass(slots=True)
class DeviceWriteStats:
    """What the writer took in and stored for one device."""

    kind: str
    items: int = 0
    """Frames, events or pulses appended (buffered ones included)."""
    raw_bytes: int = 0
    """Uncompressed payload bytes appended."""
    stored_bytes: int = 0
    """Bytes the device's datasets occupy in the file (after compression, flushed data only)."""
    uncompressed_chunks: int = 0
    """Chunks stored without their compression while the writer was behind (EVT words)."""


def new_series(
    group: h5py.Group, name: str, dtype: DTypeLike, opts: Mapping[str, Any], chunk: int = SMALL_CHUNK
) -> h5py.Dataset:
    """An empty, growable 1-D dataset (its units and compression filter named: rigd.take.units)."""
    return label(
        group.create_dataset(name, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(chunk,), **opts)
    )


def _write_slot(ds: h5py.Dataset, slot: int, start: int, data: NDArray[Any]) -> None:
    ds[slot, start : start + data.shape[0]] = data


def _event_columns(ev: EventArray, lo: int, hi: int) -> dict[str, NDArray[Any]]:
    """Events [lo, hi) as stored: polarity as 0/1, `t` last (see the module docstring)."""
    return {
        Events.X: ev.x[lo:hi],
        Events.Y: ev.y[lo:hi],
        Events.P: (ev.p[lo:hi] > 0).astype(np.uint8),
        Events.T: ev.t[lo:hi],
    }


def check_event_batch(
    events: EventArray,
    where: str,
    last_t: int | None,
    seen: int,
    width: int,
    height: int,
    *,
    within: bool = True,
    geometry: bool = True,
) -> None:
    """Refuse a batch (TakeError) that would break a sensor's time order or geometry; `seen`:
    events the sensor stored before it, `last_t`: the time of the last one. `within=False`
    skips the order of the events inside the batch: for events the production EVT decoder made,
    which never emits one earlier than the last (it counts such words as skipped), so checking
    them again would only cost the writer thread; where the batch meets the previous one is
    still checked, and the geometry unless `geometry=False` (a packet whose decoder had the
    take's geometry, `EvtChunk.geometry`)."""
    n = len(events)
    t = events.t
    if last_t is not None and int(t[0]) < last_t:
        raise TakeError(
            f"{where}: event 0 of the batch (#{seen} of the sensor) has "
            f"t={int(t[0])} us before the previous event at {last_t} us; batch of {n} refused"
        )
    bad = np.flatnonzero(t[1:] < t[:-1]) if within else np.empty(0, np.intp)
    if len(bad):
        i = int(bad[0]) + 1
        raise TakeError(
            f"{where}: event {i} of the batch (#{seen + i} of the sensor) "
            f"has t={int(t[i])} us before event {i - 1} at {int(t[i - 1])} us; batch of {n} refused"
        )
    for axis, arr, limit in (("x", events.x, width), ("y", events.y, height)) if geometry else ():
        if int(arr.max()) >= limit:
            i = int(np.argmax(arr >= limit))
            raise TakeError(
                f"{where}: event {i} of the batch has {axis}={int(arr[i])} outside the sensor's "
                f"{width}x{height} geometry; batch of {n} refused"
            )


class TriggerIn:
    """An event sensor's trigger-in edges (`<sensor>/trigger`), buffered and written in blocks;
    shared by both ways of storing the events (columns, `EventSink`; EVT words, `EvtWordsSink`)."""

    __slots__ = ("n_trig_buffered", "n_trig_written", "trig", "trig_host_parts", "trig_parts")
    trig: dict[str, h5py.Dataset]
    trig_parts: list[TriggerEvents]
    trig_host_parts: list[NDArray[np.int64]]
    n_trig_buffered: int
    n_trig_written: int

    def add_triggers(self, triggers: TriggerEvents, host_time_ns: int | None) -> None:
        n = len(triggers)
        if n == 0:
            return
        self.trig_parts.append(triggers)
        self.trig_host_parts.append(np.full(n, -1 if host_time_ns is None else int(host_time_ns), np.int64))
        self.n_trig_buffered += n
        if self.n_trig_buffered >= _SMALL_BLOCK:
            self.write_triggers()

    def write_triggers(self) -> None:
        if not self.n_trig_buffered:
            return
        tr = TriggerEvents.concatenate(self.trig_parts)
        host = np.concatenate(self.trig_host_parts)
        start = self.n_trig_written
        cols: list[tuple[str, NDArray[Any]]] = [
            (TriggerEdges.T, tr.t),
            (TriggerEdges.T_DEVICE, tr.t),
            (TriggerEdges.P, tr.p),
            (TriggerEdges.CHANNEL, tr.channel),
            (TriggerEdges.HOST_TIME_NS, host),
        ]
        for key, data in cols:
            if key in self.trig:  # a resumed 1.0 take has no host_time_ns
                append_rows(self.trig[key], start, data)
        self.n_trig_written += len(tr)
        self.trig_parts, self.trig_host_parts, self.n_trig_buffered = [], [], 0


@dataclass(slots=True)
class EventSink(TriggerIn):
    """One event sensor: `/events/<name>` and its trigger-in group."""

    name: str
    group: h5py.Group
    width: int
    height: int
    ds: dict[str, h5py.Dataset]
    trig: dict[str, h5py.Dataset]
    chunk: int
    parts: list[EventArray] = field(default_factory=list)
    n_buffered: int = 0
    n_written: int = 0
    last_t: int | None = None
    trig_parts: list[TriggerEvents] = field(default_factory=list)
    trig_host_parts: list[NDArray[np.int64]] = field(default_factory=list)
    n_trig_buffered: int = 0
    n_trig_written: int = 0
    tail_ds: dict[str, h5py.Dataset] = field(default_factory=dict)
    tail_meta: NDArray[np.int64] = field(default_factory=lambda: np.zeros((2, 2), np.int64))
    """Per tail slot: [first row, rows held]; mirrors the group attr tail_meta."""
    tail_slot: int = 0
    """Slot the last flush wrote."""
    appendable: bool = True
    """False for a resumed take: its main datasets may end in a partial chunk."""
    stats: DeviceWriteStats = field(default_factory=lambda: DeviceWriteStats("event_sensor"))

    @classmethod
    def create(
        cls, name: str, g: h5py.Group, width: int, height: int, chunk: int, opts: Mapping[str, Any]
    ) -> Self:
        """Lay out a new sensor's datasets in its (already created) group."""
        g.attrs[Device.WIDTH], g.attrs[Device.HEIGHT] = int(width), int(height)
        ds = {k: new_series(g, k, dt, opts, chunk) for k, dt in EVENT_DTYPES.items()}
        # 0 while recording: t holds device time as is. Finalize sets the real offset.
        g.create_dataset(Events.T_OFFSET, data=np.int64(0))
        tg = g.create_group(Events.TRIGGER)
        trig = {k: new_series(tg, k, dt, {}) for k, dt in TRIGGER_DTYPES.items()}
        return cls(name, g, int(width), int(height), ds, trig, chunk)

    @classmethod
    def reopen(cls, name: str, g: h5py.Group, where: str, default_chunk: int) -> Self:
        """The sink of a resumed take, from what `check_repair` left consistent."""
        ds = {k: require_dataset(g, k, where) for k in EVENT_DTYPES}
        tg = require_group(g, Events.TRIGGER, where)
        # A 1.0 take has no host_time_ns.
        trig = {
            k: require_dataset(tg, k, where)
            for k in TRIGGER_DTYPES
            if k in tg or k != TriggerEdges.HOST_TIME_NS
        }
        n = int(ds[Events.T].shape[0])
        missing = [k for k in (Device.WIDTH, Device.HEIGHT) if k not in g.attrs]
        if missing:
            raise TakeFormatError(f"{where}: {g.name}: missing attribute(s) {missing}")
        sink = cls(
            name,
            g,
            int(g.attrs[Device.WIDTH]),
            int(g.attrs[Device.HEIGHT]),
            ds,
            trig,
            int(ds[Events.T].chunks[0]) if ds[Events.T].chunks else default_chunk,
            appendable=False,
            n_written=n,
            last_t=int(ds[Events.T][n - 1]) if n else None,
            n_trig_written=int(trig[TriggerEdges.T].shape[0]),
        )
        sink.stats.items = n
        return sink

    def datasets(self) -> list[h5py.Dataset]:
        return [*self.ds.values(), *self.trig.values()]

    def _check_batch(self, events: EventArray, where: str) -> None:
        """Refuse a batch that would break the sensor's time order or geometry."""
        check_event_batch(
            events, where, self.last_t, self.n_written + self.n_buffered, self.width, self.height
        )

    def add_events(self, events: EventArray, path: Path) -> None:
        """Buffer a batch (device clock), checked whole before any of it is kept."""
        n = len(events)
        if n == 0:
            return
        self._check_batch(events, f"{path}: /{EVENTS_GROUP}/{self.name}")
        self.parts.append(events)
        self.n_buffered += n
        self.last_t = int(events.t[-1])
        self.stats.items += n
        self.stats.raw_bytes += 13 * n
        if self.n_buffered >= max(self.chunk, EVENT_WRITE_BLOCK):
            self.write_events(whole_chunks_only=True)

    def write_events(self, *, whole_chunks_only: bool) -> None:
        """Append the buffered events; `whole_chunks_only` keeps the rest past the last whole
        chunk buffered, so a compressed chunk is never rewritten by the next append."""
        if not self.n_buffered:
            return
        ev = EventArray.concatenate(self.parts)
        n = len(ev)
        if whole_chunks_only:
            total = self.n_written + n
            n = total - total % self.chunk - self.n_written
            if n <= 0:
                return
        for key, data in _event_columns(ev, 0, n).items():
            append_rows(self.ds[key], self.n_written, data)
        self.n_written += n
        rest = ev[n:]
        self.parts = [rest] if len(rest) else []
        self.n_buffered = len(rest)

    def write_tail(self) -> None:
        """Put the buffered rows past the last whole chunk in a tail slot (flush only)."""
        n = self.n_buffered
        if n == 0 or self.chunk <= 0:
            return
        meta = self.tail_meta
        slot = choose_tail_slot(meta, self.tail_slot, self.n_written)
        if not self.tail_ds:
            self.tail_ds = create_tail_slots(self.group, self.chunk)
        ev = EventArray.concatenate(self.parts)
        have = int(meta[slot, 1])
        for key, data in _event_columns(ev, have, n).items():
            _write_slot(self.tail_ds[key], slot, have, data)
        meta[slot, 1] = n
        self.tail_slot = slot
        self.group.attrs.modify(Events.TAIL_META, meta)

    def drop_tails(self) -> None:
        """After everything is in the main datasets (close, fail, finalize) the tails go."""
        drop_tail_slots(self.group)
        self.tail_ds = {}
        self.tail_meta[:] = 0

    # -- the EventStore interface (rigd.take.event_store) -------------------------------
    def append_packet(self, packet: EventPacket, path: Path) -> None:
        """Store a packet's decoded events as columns, and its trigger edges."""
        if packet.n_events:
            self.add_events(packet.events, path)
        self.add_triggers(packet.triggers, packet.host_time_ns)

    def write_buffers(self, *, final: bool) -> None:
        self.write_events(whole_chunks_only=not final)
        if not final:
            self.write_tail()
        self.write_triggers()

    def set_compress(self, on: bool) -> None:
        """Columns are compressed by HDF5's filter on every chunk; there is nothing to switch."""

    def first_time(self) -> int | None:
        written = self.ds[Events.T].shape[0]
        if written:
            return int(self.ds[Events.T][0])
        return int(self.parts[0].t[0]) if self.parts else None

    def events_in_take(self) -> int:
        return self.n_written

    def finalize_times(self, finalizer: Finalizer, cmap: ClockMap, t_offset: int) -> None:
        finalizer.finalize_columns(self, cmap, t_offset)


@dataclass(slots=True)
class CameraSink:
    """One camera: `/frames/<name>`, images written per frame, timestamps in blocks."""

    name: str
    group: h5py.Group
    shape: tuple[int, ...]
    dtype: np.dtype[Any]
    images: h5py.Dataset
    series: dict[str, h5py.Dataset]
    pixel_format: str
    n_frames: int = 0
    n_series_written: int = 0
    buf: dict[str, list[int]] = field(default_factory=lambda: {k: [] for k in FRAME_SERIES})
    stats: DeviceWriteStats = field(default_factory=lambda: DeviceWriteStats("rgb_camera"))
    alloc: int = 0
    """Frames the images dataset has room for (kept here: no HDF5 metadata call per frame)."""
    direct: bool = False
    """Frames are stored unfiltered, one per chunk: each is written as its chunk, bypassing
    HDF5's selection and chunk cache (a quarter of the time of `images[n] = img`)."""

    @staticmethod
    def check_format(
        pixel_format: str | None, shape: tuple[int, ...], dtype: np.dtype[Any], where: str
    ) -> str:
        """The pixel format frames of this shape and dtype are stored in; TakeError naming
        `where` when the declared format cannot hold them."""
        by_shape = "rgb8" if len(shape) == 3 else "mono8"
        fmt = pixel_format or by_shape
        if fmt not in PIXEL_FORMATS:
            raise TakeError(f"{where}: pixel format {fmt!r} is not one of {', '.join(PIXEL_FORMATS)}")
        if is_bayer(fmt) and (len(shape) != 2 or dtype != np.uint8):
            raise TakeError(f"{where}: {fmt} frames are (H, W) uint8 mosaics, declared {shape} {dtype}")
        if fmt == "rgb8" and len(shape) != 3:
            raise TakeError(f"{where}: rgb8 frames are (H, W, 3), declared {shape}")
        return fmt

    @classmethod
    def create(
        cls,
        name: str,
        g: h5py.Group,
        shape: tuple[int, ...],
        dtype: np.dtype[Any],
        opts: Mapping[str, Any],
        pixel_format: str,
    ) -> Self:
        """Lay out a new camera's datasets in its (already created) group."""
        g.attrs[Device.HEIGHT], g.attrs[Device.WIDTH] = shape[0], shape[1]
        g.attrs[Frames.CHANNELS] = shape[2] if len(shape) == 3 else 1
        g.attrs[Frames.DTYPE] = dtype.str
        g.attrs[Frames.PIXEL_FORMAT] = pixel_format
        if is_bayer(pixel_format):
            g.attrs[Frames.BAYER_PATTERN] = BAYER_PATTERNS[pixel_format]
        images = g.create_dataset(
            Frames.IMAGES, shape=(0, *shape), maxshape=(None, *shape), dtype=dtype, chunks=(1, *shape), **opts
        )
        series = {k: new_series(g, k, np.int64, {}) for k in FRAME_SERIES}
        series[Frames.T_EXPOSURE_START].attrs[Frames.UNITS] = "us"
        cam = cls(name, g, shape, dtype, images, series, pixel_format)
        cam.direct = images.id.get_create_plist().get_nfilters() == 0
        return cam

    @classmethod
    def reopen(cls, name: str, g: h5py.Group, where: str) -> Self:
        """The sink of a resumed take, from what `check_repair` left consistent."""
        images = require_dataset(g, Frames.IMAGES, where)
        series = {k: require_dataset(g, k, where) for k in FRAME_SERIES}
        n = int(series[Frames.T_EXPOSURE_START].shape[0])
        shape = tuple(int(s) for s in images.shape[1:])
        fmt = stored_pixel_format(g.attrs, shape, where)
        cam = cls(name, g, shape, np.dtype(images.dtype), images, series, fmt, n_frames=n, n_series_written=n)
        cam.stats.items = n
        cam.alloc = int(images.shape[0])
        return cam

    def datasets(self) -> list[h5py.Dataset]:
        return [self.images, *self.series.values()]

    def add_frame(self, frame: Frame, path: Path) -> None:
        """Write the image now (one HDF5 write) and buffer its timestamps (device clock)."""
        img = frame.image
        if img.shape != self.shape or img.dtype != self.dtype:
            raise TakeError(
                f"{path}: /{FRAMES_GROUP}/{self.name}/images: frame {self.n_frames} has shape {img.shape} "
                f"{img.dtype}, declared {self.shape} {self.dtype}"
            )
        if frame.pixel_format is not None and frame.pixel_format != self.pixel_format:
            raise TakeError(
                f"{path}: /{FRAMES_GROUP}/{self.name}/images: frame {self.n_frames} is "
                f"{frame.pixel_format}, the camera was declared {self.pixel_format}"
            )
        n = self.n_frames
        if self.alloc <= n:
            self.alloc = n + _FRAME_BLOCK
            self.images.resize((self.alloc, *self.shape))
        data = np.ascontiguousarray(img)
        if self.direct:
            write_chunk(self.images, (n, *(0 for _ in self.shape)), data)
        else:
            self.images[n] = data
        self.n_frames = n + 1
        t = int(frame.t_exposure_start_us)
        for key, value in (
            (Frames.T_EXPOSURE_START, t),
            (Frames.T_EXPOSURE_START_DEVICE, t),
            (Frames.EXPOSURE, frame.exposure_us),
            (Frames.FRAME_COUNTER, frame.frame_counter),
            (Frames.PULSE_INDEX, frame.pulse_index),
            (Frames.HOST_TIME_NS, frame.host_time_ns),
        ):
            self.buf[key].append(int(value))
        self.stats.items += 1
        self.stats.raw_bytes += int(img.nbytes) + 48
        if self.n_frames - self.n_series_written >= _SMALL_BLOCK:
            self.write_series()

    def write_series(self) -> None:
        if self.n_frames - self.n_series_written:
            for key, values in self.buf.items():
                append_rows(self.series[key], self.n_series_written, np.asarray(values, dtype=np.int64))
                values.clear()
            self.n_series_written = self.n_frames

    def trim_images(self) -> None:
        """Drop the preallocated frames no image was written to."""
        if self.alloc != self.n_frames:
            self.images.resize((self.n_frames, *self.shape))
            self.alloc = self.n_frames


@dataclass(slots=True)
class PulseSink:
    """The trigger box pulse log, `/trigger/pulses` (already rig time)."""

    ds: dict[str, h5py.Dataset]
    parts: list[PulseBatch] = field(default_factory=list)
    n_buffered: int = 0
    n_written: int = 0
    stats: DeviceWriteStats = field(default_factory=lambda: DeviceWriteStats("trigger"))

    @classmethod
    def create(cls, g: h5py.Group) -> Self:
        return cls({k: new_series(g, k, np.int64, {}) for k in PULSE_SERIES})

    @classmethod
    def reopen(cls, g: h5py.Group, where: str) -> Self:
        sink = cls({k: require_dataset(g, k, where) for k in PULSE_SERIES})
        sink.n_written = int(sink.ds[Pulses.INDEX].shape[0])
        sink.stats.items = sink.n_written
        return sink

    def datasets(self) -> list[h5py.Dataset]:
        return list(self.ds.values())

    def add(self, batch: PulseBatch) -> None:
        if len(batch) == 0:
            return
        self.parts.append(batch)
        self.n_buffered += len(batch)
        self.stats.items += len(batch)
        self.stats.raw_bytes += 24 * len(batch)
        if self.n_buffered >= _SMALL_BLOCK:
            self.write()

    def write(self) -> None:
        if not self.n_buffered:
            return
        for key in PULSE_SERIES:
            data = np.concatenate([np.asarray(getattr(b, key), dtype=np.int64) for b in self.parts])
            append_rows(self.ds[key], self.n_written, data)
        self.n_written += self.n_buffered
        self.parts, self.n_buffered = [], 0
