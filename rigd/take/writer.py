"""TakeWriter: streams one take into an HDF5 file, then maps it to rig time on finalize.

Used by exactly one writer thread. While recording every timestamp is stored in its
device clock (the clock maps are only known once all pulses are in); `finalize` rewrites
the times in place, chunk by chunk, so memory stays constant however long the take is.
The layout is documented in docs/take-format.md; names come from `rigd.core.schema`.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Self

import h5py
import hdf5plugin
import numpy as np
from numpy.typing import DTypeLike, NDArray

from drivers.base import DeviceInfo, PulseBatch
from rigd.config import WriterConfig
from rigd.core.errors import TakeError
from rigd.core.events import EventArray, TriggerEvents
from rigd.core.frames import Frame
from rigd.core.schema import (
    CONFIG_DATASET,
    EVENT_DTYPES,
    EVENTS_GROUP,
    FRAME_SERIES,
    FRAMES_GROUP,
    PULSE_SERIES,
    SCHEMA_NAME,
    SCHEMA_VERSION,
    SYNC_GROUP,
    TRIGGER_DTYPES,
    TRIGGER_GROUP,
    SyncReport,
)
from rigd.core.timebase import ClockMap

log = logging.getLogger(__name__)

_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_-]{0,31}$")
#: Frames are allocated in blocks of this many, so the images dataset is not resized per frame.
_FRAME_BLOCK = 64
#: Small per-item buffers (frame timestamps, triggers, pulses) are written when this full.
_SMALL_BLOCK = 4096
#: Chunk length of small 1-D datasets (frame times, triggers, pulses, ms_to_idx).
_SMALL_CHUNK = 4096
#: ms_to_idx entries computed per step on finalize (bounds memory on sparse, long takes).
_MS_STEP = 1 << 20
#: gzip level: 1 keeps write speed usable; with the shuffle filter it loses little ratio.
_GZIP_LEVEL = 1


def compression_options(codec: str, *, shuffle: bool) -> dict[str, Any]:
    """h5py dataset keywords for a WriterConfig codec name.

    The byte-shuffle filter groups the constant high bytes of int64 times and uint16
    coordinates, which is what makes the fast codecs effective on event streams.
    """
    opts: dict[str, Any]
    if codec == "none":
        return {}
    if codec == "lz4":
        opts = dict(hdf5plugin.LZ4())
    elif codec == "zstd":
        opts = dict(hdf5plugin.Zstd(clevel=3))
    elif codec == "gzip":
        opts = {"compression": "gzip", "compression_opts": _GZIP_LEVEL}
    else:
        raise TakeError(f"unknown compression {codec!r} (use none, lz4, zstd or gzip)")
    if shuffle:
        opts["shuffle"] = True
    return opts


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


@dataclass(slots=True)
class _EventSink:
    name: str
    group: h5py.Group
    width: int
    height: int
    ds: dict[str, h5py.Dataset]
    trig: dict[str, h5py.Dataset]
    parts: list[EventArray] = field(default_factory=list)
    n_buffered: int = 0
    n_written: int = 0
    last_t: int | None = None
    trig_parts: list[TriggerEvents] = field(default_factory=list)
    n_trig_buffered: int = 0
    n_trig_written: int = 0
    stats: DeviceWriteStats = field(default_factory=lambda: DeviceWriteStats("event_sensor"))


@dataclass(slots=True)
class _CameraSink:
    name: str
    group: h5py.Group
    shape: tuple[int, ...]
    dtype: np.dtype[Any]
    images: h5py.Dataset
    series: dict[str, h5py.Dataset]
    n_frames: int = 0
    n_series_written: int = 0
    buf: dict[str, list[int]] = field(default_factory=lambda: {k: [] for k in FRAME_SERIES})
    stats: DeviceWriteStats = field(default_factory=lambda: DeviceWriteStats("rgb_camera"))


def _append(ds: h5py.Dataset, start: int, data: NDArray[Any]) -> None:
    end = start + data.shape[0]
    if ds.shape[0] < end:
        ds.resize((end, *ds.shape[1:]))
    ds[start:end] = data


class TakeWriter:
    """Writes one take file; see docs/take-format.md for the layout it produces."""

    def __init__(
        self,
        path: str | Path,
        *,
        rig_config_json: str,
        take_id: str,
        config: WriterConfig,
        rigd_version: str,
    ) -> None:
        self.path = Path(path)
        self._cfg = config
        self._ev_opts = compression_options(config.event_compression, shuffle=True)
        self._small_opts = compression_options(config.event_compression, shuffle=True)
        self._frame_opts = compression_options(config.frame_compression, shuffle=False)
        try:
            json.loads(rig_config_json)
        except json.JSONDecodeError as exc:
            raise TakeError(f"{self.path}: rig_config_json is not valid JSON: {exc}") from exc
        try:
            # Default (earliest) file format: no superblock status flags, so a take left by a
            # crashed process opens without h5clear.
            self._f = h5py.File(self.path, "w-")
        except (OSError, FileExistsError) as exc:
            raise TakeError(f"cannot create take file {self.path}: {exc}") from exc
        self._closed = False
        self._state = "recording"
        f = self._f
        f.attrs["schema"] = SCHEMA_NAME
        f.attrs["schema_version"] = SCHEMA_VERSION
        f.attrs["status"] = "recording"
        f.attrs["take_id"] = take_id
        f.attrs["created_utc"] = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        f.attrs["rigd_version"] = rigd_version
        f.attrs["time_domain"] = "device"
        f.create_dataset(CONFIG_DATASET, data=rig_config_json, dtype=h5py.string_dtype("utf-8"))
        f.create_group(EVENTS_GROUP)
        f.create_group(FRAMES_GROUP)
        f.create_group(SYNC_GROUP)
        trig = f.create_group(TRIGGER_GROUP)
        pulses = trig.create_group("pulses")
        self._pulse_ds = {k: self._series(pulses, k, np.int64, self._small_opts) for k in PULSE_SERIES}
        self._pulse_parts: list[PulseBatch] = []
        self._n_pulse_buffered = 0
        self._n_pulses_written = 0
        self._pulse_stats = DeviceWriteStats("trigger")
        self._has_trigger = False
        self._events: dict[str, _EventSink] = {}
        self._cameras: dict[str, _CameraSink] = {}
        f.flush()
        log.info("take %s created (%s)", self.path, take_id)

    # -- setup -------------------------------------------------------------------------
    @staticmethod
    def _series(
        group: h5py.Group, name: str, dtype: DTypeLike, opts: Mapping[str, Any], chunk: int = _SMALL_CHUNK
    ) -> h5py.Dataset:
        return group.create_dataset(name, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(chunk,), **opts)

    def _check_new_device(self, name: str) -> None:
        self._check_writable()
        if not _NAME_RE.match(name):
            raise TakeError(
                f"{self.path}: device name {name!r} is not a valid take name ({_NAME_RE.pattern})"
            )
        if name in self._events or name in self._cameras:
            raise TakeError(f"{self.path}: device {name!r} added twice")

    @staticmethod
    def _info_attrs(obj: h5py.HLObject, info: DeviceInfo, settings_json: str | None) -> None:
        for key, value in info.model_dump().items():
            if isinstance(value, str):  # scalar identity fields as plain attributes
                obj.attrs[key] = value
        obj.attrs["info_json"] = info.model_dump_json()
        if settings_json is not None:
            obj.attrs["settings_json"] = settings_json

    def add_trigger(self, info: DeviceInfo) -> None:
        """Record the trigger box identity on `/trigger`."""
        self._check_writable()
        self._info_attrs(self._f[TRIGGER_GROUP], info, None)
        self._has_trigger = True

    def add_camera(
        self, name: str, info: DeviceInfo, shape: tuple[int, ...], dtype: DTypeLike, settings_json: str
    ) -> None:
        """Create `/frames/<name>`; frames must then match `shape` and `dtype` exactly."""
        self._check_new_device(name)
        shape = tuple(int(s) for s in shape)
        if len(shape) not in (2, 3) or min(shape) <= 0:
            raise TakeError(f"{self.path}: camera {name!r}: frame shape {shape} is not (H, W) or (H, W, C)")
        dt = np.dtype(dtype)
        g = self._f[FRAMES_GROUP].create_group(name)
        self._info_attrs(g, info, settings_json)
        g.attrs["height"], g.attrs["width"] = shape[0], shape[1]
        g.attrs["channels"] = shape[2] if len(shape) == 3 else 1
        g.attrs["dtype"] = dt.str
        images = g.create_dataset(
            "images",
            shape=(0, *shape),
            maxshape=(None, *shape),
            dtype=dt,
            chunks=(1, *shape),
            **self._frame_opts,
        )
        series = {k: self._series(g, k, np.int64, self._small_opts) for k in FRAME_SERIES}
        series["t_exposure_start_us"].attrs["units"] = "us"
        self._cameras[name] = _CameraSink(name, g, shape, dt, images, series)

    def add_event_sensor(
        self, name: str, info: DeviceInfo, width: int, height: int, settings_json: str
    ) -> None:
        """Create `/events/<name>` with DSEC-compatible datasets and its trigger-in group."""
        self._check_new_device(name)
        if not (0 < width <= 65536 and 0 < height <= 65536):
            raise TakeError(f"{self.path}: event sensor {name!r}: geometry {width}x{height} out of range")
        g = self._f[EVENTS_GROUP].create_group(name)
        self._info_attrs(g, info, settings_json)
        g.attrs["width"], g.attrs["height"] = int(width), int(height)
        chunk = self._cfg.event_chunk
        ds = {k: self._series(g, k, dt, self._ev_opts, chunk) for k, dt in EVENT_DTYPES.items()}
        # 0 while recording: t holds device time as is. Finalize sets the real offset.
        g.create_dataset("t_offset", data=np.int64(0))
        tg = g.create_group("trigger")
        trig = {k: self._series(tg, k, dt, self._small_opts) for k, dt in TRIGGER_DTYPES.items()}
        self._events[name] = _EventSink(name, g, int(width), int(height), ds, trig)

    # -- appends -----------------------------------------------------------------------
    def _check_writable(self) -> None:
        if self._closed:
            raise TakeError(f"{self.path}: take is closed")
        if self._state != "recording":
            raise TakeError(f"{self.path}: take is {self._state}; no more data can be written")

    def _sensor(self, name: str) -> _EventSink:
        self._check_writable()
        try:
            return self._events[name]
        except KeyError:
            raise TakeError(f"{self.path}: unknown event sensor {name!r} (add_event_sensor first)") from None

    def append_pulses(self, batch: PulseBatch) -> None:
        """Buffer trigger box pulses (already rig time)."""
        self._check_writable()
        if len(batch) == 0:
            return
        self._pulse_parts.append(batch)
        self._n_pulse_buffered += len(batch)
        self._pulse_stats.items += len(batch)
        self._pulse_stats.raw_bytes += 24 * len(batch)
        if self._n_pulse_buffered >= _SMALL_BLOCK:
            self._write_pulses()

    def append_frame(self, name: str, frame: Frame) -> None:
        """Write one frame image (one HDF5 write) and buffer its timestamps (device clock)."""
        self._check_writable()
        try:
            cam = self._cameras[name]
        except KeyError:
            raise TakeError(f"{self.path}: unknown camera {name!r} (add_camera first)") from None
        img = frame.image
        if img.shape != cam.shape or img.dtype != cam.dtype:
            raise TakeError(
                f"{self.path}: /{FRAMES_GROUP}/{name}/images: frame {cam.n_frames} has shape {img.shape} "
                f"{img.dtype}, declared {cam.shape} {cam.dtype}"
            )
        n = cam.n_frames
        if cam.images.shape[0] <= n:
            cam.images.resize((n + _FRAME_BLOCK, *cam.shape))
        cam.images[n] = np.ascontiguousarray(img)
        cam.n_frames = n + 1
        t = int(frame.t_exposure_start_us)
        for key, value in (
            ("t_exposure_start_us", t),
            ("t_exposure_start_device_us", t),
            ("exposure_us", frame.exposure_us),
            ("frame_counter", frame.frame_counter),
            ("pulse_index", frame.pulse_index),
            ("host_time_ns", frame.host_time_ns),
        ):
            cam.buf[key].append(int(value))
        cam.stats.items += 1
        cam.stats.raw_bytes += int(img.nbytes) + 48
        if cam.n_frames - cam.n_series_written >= _SMALL_BLOCK:
            self._write_camera(cam)

    def append_events(self, name: str, events: EventArray) -> None:
        """Buffer events (device clock); checked whole before any of the batch is kept."""
        sink = self._sensor(name)
        n = len(events)
        if n == 0:
            return
        where = f"{self.path}: /{EVENTS_GROUP}/{name}"
        t = events.t
        if sink.last_t is not None and int(t[0]) < sink.last_t:
            raise TakeError(
                f"{where}: event 0 of the batch (#{sink.n_written + sink.n_buffered} of the sensor) has "
                f"t={int(t[0])} us before the previous event at {sink.last_t} us; batch of {n} refused"
            )
        bad = np.flatnonzero(t[1:] < t[:-1])
        if bad.size:
            i = int(bad[0]) + 1
            raise TakeError(
                f"{where}: event {i} of the batch (#{sink.n_written + sink.n_buffered + i} of the sensor) "
                f"has t={int(t[i])} us before event {i - 1} at {int(t[i - 1])} us; batch of {n} refused"
            )
        for axis, arr, limit in (("x", events.x, sink.width), ("y", events.y, sink.height)):
            if int(arr.max()) >= limit:
                i = int(np.argmax(arr >= limit))
                raise TakeError(
                    f"{where}: event {i} of the batch has {axis}={int(arr[i])} outside the sensor's "
                    f"{sink.width}x{sink.height} geometry; batch of {n} refused"
                )
        sink.parts.append(events)
        sink.n_buffered += n
        sink.last_t = int(t[-1])
        sink.stats.items += n
        sink.stats.raw_bytes += 13 * n
        if sink.n_buffered >= self._cfg.event_chunk:
            self._write_events(sink, whole_chunks_only=True)

    def append_triggers(self, name: str, triggers: TriggerEvents) -> None:
        """Buffer trigger-in edges of an event sensor (device clock)."""
        sink = self._sensor(name)
        if len(triggers) == 0:
            return
        sink.trig_parts.append(triggers)
        sink.n_trig_buffered += len(triggers)
        if sink.n_trig_buffered >= _SMALL_BLOCK:
            self._write_triggers(sink)

    # -- buffer writes -----------------------------------------------------------------
    def _write_events(self, sink: _EventSink, *, whole_chunks_only: bool) -> None:
        if not sink.n_buffered:
            return
        ev = EventArray.concatenate(sink.parts)
        n = len(ev)
        if whole_chunks_only:
            # End on a chunk boundary so compressed chunks are not rewritten on the next append.
            total = sink.n_written + n
            n = total - total % self._cfg.event_chunk - sink.n_written
            if n <= 0:
                return
        cols: dict[str, NDArray[Any]] = {
            "x": ev.x[:n],
            "y": ev.y[:n],
            "p": (ev.p[:n] > 0).astype(np.uint8),
            "t": ev.t[:n],
        }
        for key, data in cols.items():
            _append(sink.ds[key], sink.n_written, data)
        sink.n_written += n
        rest = ev[n:]
        sink.parts = [rest] if len(rest) else []
        sink.n_buffered = len(rest)

    def _write_triggers(self, sink: _EventSink) -> None:
        if not sink.n_trig_buffered:
            return
        tr = TriggerEvents.concatenate(sink.trig_parts)
        start = sink.n_trig_written
        for key, data in (("t", tr.t), ("t_device", tr.t), ("p", tr.p), ("channel", tr.channel)):
            _append(sink.trig[key], start, data)
        sink.n_trig_written += len(tr)
        sink.trig_parts, sink.n_trig_buffered = [], 0

    def _write_camera(self, cam: _CameraSink) -> None:
        k = cam.n_frames - cam.n_series_written
        if k:
            for key, values in cam.buf.items():
                _append(cam.series[key], cam.n_series_written, np.asarray(values, dtype=np.int64))
                values.clear()
            cam.n_series_written = cam.n_frames

    def _trim_camera(self, cam: _CameraSink) -> None:
        if cam.images.shape[0] != cam.n_frames:
            cam.images.resize((cam.n_frames, *cam.shape))

    def _write_pulses(self) -> None:
        if not self._n_pulse_buffered:
            return
        parts = self._pulse_parts
        start = self._n_pulses_written
        for key in PULSE_SERIES:
            data = np.concatenate([np.asarray(getattr(b, key), dtype=np.int64) for b in parts])
            _append(self._pulse_ds[key], start, data)
        self._n_pulses_written += self._n_pulse_buffered
        self._pulse_parts, self._n_pulse_buffered = [], 0

    def _write_all(self) -> None:
        for sink in self._events.values():
            self._write_events(sink, whole_chunks_only=False)
            self._write_triggers(sink)
        for cam in self._cameras.values():
            self._write_camera(cam)
            self._trim_camera(cam)
        self._write_pulses()

    def flush(self) -> None:
        """Write every buffer and flush HDF5, so a crash from here on loses nothing written.

        Cheap: buffered data is written once; partial event chunks are rewritten later.
        """
        if self._closed:
            raise TakeError(f"{self.path}: take is closed")
        if self._state == "recording":
            self._write_all()
        self._f.flush()

    # -- finalize ----------------------------------------------------------------------
    def finalize(
        self,
        maps: dict[str, ClockMap],
        frame_pulse_index: dict[str, NDArray[np.int64]],
        report: SyncReport,
    ) -> None:
        """Map every stored time to rig time, build the DSEC index and mark the take complete."""
        self._check_writable()
        self._write_all()
        self._f.flush()
        where = str(self.path)
        for name in (*self._cameras, *self._events):
            if name not in maps:
                raise TakeError(f"{where}: finalize: no clock map for device {name!r}")
        for name, idx in frame_pulse_index.items():
            if name not in self._cameras:
                raise TakeError(f"{where}: finalize: frame_pulse_index names unknown camera {name!r}")
            if np.asarray(idx).shape != (self._cameras[name].n_frames,):
                raise TakeError(
                    f"{where}: finalize: frame_pulse_index[{name!r}] has shape {np.asarray(idx).shape}, "
                    f"expected ({self._cameras[name].n_frames},) (frames written)"
                )
        t_offset, source = self._choose_t_offset(maps, report)
        f = self._f
        # If the process dies while times are being rewritten, this says so (see the docs).
        f.attrs["finalize_started_utc"] = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        f.flush()
        for name, sink in self._events.items():
            self._finalize_events(sink, maps[name], t_offset)
            sink.group.attrs["t_offset_source"] = source
        for name, cam in self._cameras.items():
            cmap = maps[name]
            dev = cam.series["t_exposure_start_device_us"][...]
            cam.series["t_exposure_start_us"][...] = cmap.to_rig(dev)
            if name in frame_pulse_index:
                cam.series["pulse_index"][...] = np.asarray(frame_pulse_index[name], dtype=np.int64)
        self._write_sync(maps, report)
        f.attrs["time_domain"] = "rig"
        f.attrs["status"] = "complete"
        del f.attrs["finalize_started_utc"]
        f.attrs["finalized_utc"] = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        f.flush()
        self._state = "complete"
        log.info("take %s finalized (t_offset %d us)", self.path, t_offset)

    def _choose_t_offset(self, maps: Mapping[str, ClockMap], report: SyncReport) -> tuple[int, str]:
        """One offset for all sensors: the first pulse, else the earliest event, else 0."""
        if report.t_first_pulse_us is not None:
            return int(report.t_first_pulse_us), "first_pulse"
        firsts = [
            int(maps[name].to_rig(sink.ds["t"][0:1])[0])
            for name, sink in self._events.items()
            if sink.n_written
        ]
        return (min(firsts), "first_event") if firsts else (0, "none")

    def _finalize_events(self, sink: _EventSink, cmap: ClockMap, t_offset: int) -> None:
        """Rewrite t as rig time - t_offset block by block and build ms_to_idx on the way."""
        tds = sink.ds["t"]
        n = sink.n_written
        block = max(self._cfg.event_chunk, (1 << 20) // self._cfg.event_chunk * self._cfg.event_chunk)
        last_rel = int(cmap.to_rig(tds[n - 1 : n])[0]) - t_offset if n else -1
        n_ms = last_rel // 1000 + 1 if last_rel >= 0 else 0
        ms_ds = sink.group.create_dataset(
            "ms_to_idx",
            shape=(n_ms,),
            dtype=np.uint64,
            chunks=(min(max(n_ms, 1), 1 << 16),),
            **self._small_opts,
        )
        ms_next = 0
        for start in range(0, n, block):
            stop = min(start + block, n)
            rel = cmap.to_rig(tds[start:stop]) - t_offset
            tds[start:stop] = rel
            ms_hi = min(int(rel[-1]) // 1000 + 1, n_ms) if rel[-1] >= 0 else 0
            while ms_next < ms_hi:
                step_hi = min(ms_next + _MS_STEP, ms_hi)
                thresholds = np.arange(ms_next, step_hi, dtype=np.int64) * 1000
                ms_ds[ms_next:step_hi] = (np.searchsorted(rel, thresholds, side="left") + start).astype(
                    np.uint64
                )
                ms_next = step_hi
        sink.group["t_offset"][()] = np.int64(t_offset)
        trig_dev = sink.trig["t_device"][...]
        sink.trig["t"][...] = cmap.to_rig(trig_dev)

    def _write_sync(self, maps: Mapping[str, ClockMap], report: SyncReport) -> None:
        sync = self._f[SYNC_GROUP]
        sync.create_dataset("report_json", data=report.model_dump_json(), dtype=h5py.string_dtype("utf-8"))
        devs = sync.create_group("devices")
        for name, cmap in maps.items():
            g = devs.create_group(name)
            g.attrs["device_ref_us"] = np.int64(cmap.device_ref_us)
            g.attrs["rig_ref_us"] = np.int64(cmap.rig_ref_us)
            g.attrs["rate"] = float(cmap.rate)
            g.attrs["frac_us"] = float(cmap.frac_us)
            g.attrs["drift_ppm"] = float(cmap.drift_ppm)
            dev = report.devices.get(name)
            if dev is not None:
                g.attrs["residual_rms_us"] = dev.residual_rms_us
                g.attrs["residual_max_us"] = dev.residual_max_us
                g.create_dataset("missing_pulses", data=np.asarray(dev.missing_pulses, dtype=np.int64))
                g.create_dataset("dropped_frames", data=np.asarray(dev.dropped_frames, dtype=np.int64))

    # -- end of life -------------------------------------------------------------------
    def fail(self, reason: str) -> None:
        """Mark the take failed with a reason; everything written so far stays readable."""
        if self._closed:
            raise TakeError(f"{self.path}: take is closed")
        if self._state == "complete":
            log.warning("take %s: fail(%r) after finalize ignored", self.path, reason)
            return
        try:
            if self._state == "recording":
                self._write_all()
        finally:
            self._state = "failed"
            self._f.attrs["status"] = "failed"
            self._f.attrs["failure_reason"] = reason
            self._f.flush()
            log.error("take %s marked failed: %s", self.path, reason)

    def close(self) -> None:
        """Write buffers and close. Idempotent; an unfinalized take stays "recording"."""
        if self._closed:
            return
        try:
            if self._state == "recording":
                self._write_all()
        finally:
            self._closed = True
            self._f.close()
            log.info("take %s closed (%s)", self.path, self._state)

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    @property
    def status(self) -> str:
        return self._state

    @property
    def stats(self) -> dict[str, DeviceWriteStats]:
        """Per device (and "trigger"): items and bytes taken in, bytes stored in the file."""
        out: dict[str, DeviceWriteStats] = {}
        groups: list[tuple[str, DeviceWriteStats, list[h5py.Dataset]]] = []
        for name, sink in self._events.items():
            groups.append((name, sink.stats, [*sink.ds.values(), *sink.trig.values()]))
        for name, cam in self._cameras.items():
            groups.append((name, cam.stats, [cam.images, *cam.series.values()]))
        groups.append(("trigger", self._pulse_stats, list(self._pulse_ds.values())))
        for name, st, dsets in groups:
            stored = sum(d.id.get_storage_size() for d in dsets) if not self._closed else st.stored_bytes
            st.stored_bytes = int(stored)
            out[name] = DeviceWriteStats(st.kind, st.items, st.raw_bytes, st.stored_bytes)
        return out
