"""TakeWriter: streams one take into an HDF5 file, then maps it to rig time on finalize.

Used by exactly one writer thread. While recording every timestamp is stored in its
device clock (the clock maps are only known once all pulses are in); `finalize` rewrites
the times in place, chunk by chunk, so memory stays constant however long the take is.
The layout is documented in docs/take-format.md; names come from `rigd.core.schema`.

Crash safety: `flush()` leaves the file consistent up to that point (plus a JSON journal of
the caller's loss bookkeeping); `TakeWriter.resume` reopens a take whose writer died, trims
what the kill left half-written (`check_repair`) and lets `finalize` run; a finalize cut short
is continued from its stored plan and per-block redo log (`continue_finalize`), so no time is
ever mapped twice.
"""

from __future__ import annotations

import datetime as _dt
import errno
import io
import json
import logging
import os
import re
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Self

import h5py
import hdf5plugin
import numpy as np
from numpy.typing import DTypeLike, NDArray
from pydantic import BaseModel, ConfigDict

from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.errors import TakeError, TakeFormatError, TakeInUseError, TakeTruncatedError
from rigd.core.events import EventArray, TriggerEvents
from rigd.core.frames import Frame
from rigd.core.schema import (
    CONFIG_DATASET,
    END_REASON_ATTR,
    EVENT_DTYPES,
    EVENTS_GROUP,
    FINALIZE_PLAN_ATTR,
    FINALIZE_SCRATCH,
    FINALIZE_UPTO_ATTR,
    FRAME_SERIES,
    FRAMES_GROUP,
    JOURNAL_DATASET,
    PULSE_SERIES,
    RECOVERED_ATTR,
    RECOVERY_REPORT_ATTR,
    SCHEMA_NAME,
    SCHEMA_VERSION,
    SYNC_GROUP,
    TAIL_META_ATTR,
    TAIL_PREFIX,
    TRIGGER_DTYPES,
    TRIGGER_GROUP,
    LossKind,
    SyncReport,
    encode_journal,
    has_item,
)
from rigd.core.settings import WriterConfig
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
#: Events rewritten per finalize block (rounded down to whole chunks): bounds memory and is
#: the unit of the redo log, so a crash costs at most one block of redone work.
_FINALIZE_BLOCK = 1 << 20
#: Events read per step when scanning `t` for a damaged tail.
_SCAN_BLOCK = 1 << 20
#: Smallest journal slot; a bigger journal doubles it.
_JOURNAL_MIN_BYTES = 4096
#: Writers whose file could not be closed even with its pending writes discarded: HDF5 (2.0)
#: crashes the process when the objects of such a file are freed, so they are kept.
_UNCLOSABLE: list[TakeWriter] = []
_ERRNO_RE = re.compile(r"errno = (\d+)")


def _as_oserror(exc: BaseException) -> OSError:
    """HDF5 reports some failed writes (a flush, a close) as RuntimeError; callers handle a
    file system that refuses writes as OSError, with the errno HDF5 saw (ENOSPC: disk full)."""
    if isinstance(exc, OSError):
        return exc
    m = _ERRNO_RE.search(str(exc))
    return OSError(int(m.group(1)) if m else errno.EIO, str(exc))


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


#: Root attr: the real end of a truncated take that resume extended with a hole; chunks past it
#: were never written. Removed once check_repair has trimmed them away.
TRUNCATED_EOF_ATTR = "truncated_eof"
_TRUNCATED_RE = re.compile(r"truncated file: eof = (\d+),.*stored_eof = (\d+)")


class Trim(BaseModel):
    """One group of datasets cut back by `check_repair`: what, from which lengths, and why."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    hpath: str
    """HDF5 path of the group whose datasets were trimmed, e.g. `/events/ev0/trigger`."""
    lengths_before: dict[str, int]
    after: int
    reason: str
    device: str
    what: LossKind
    lost: int
    """Items that were real data (a LossRecord count); preallocated empty frames are not."""


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


@dataclass(frozen=True, slots=True)
class _FinalizePlan:
    """What finalize maps with, stored before the first time is rewritten (see resume)."""

    t_offset: int
    source: str
    maps: dict[str, ClockMap]

    def to_json(self) -> str:
        maps = {name: [m.device_ref_us, m.rig_ref_us, m.rate, m.frac_us] for name, m in self.maps.items()}
        # json writes floats with repr(): they read back bit-exact.
        return json.dumps({"t_offset": self.t_offset, "t_offset_source": self.source, "maps": maps})

    @classmethod
    def from_json(cls, text: str, where: str) -> _FinalizePlan:
        try:
            data = json.loads(text)
            maps = {
                str(name): ClockMap(int(v[0]), int(v[1]), float(v[2]), float(v[3]))
                for name, v in data["maps"].items()
            }
            return cls(int(data["t_offset"]), str(data["t_offset_source"]), maps)
        except (json.JSONDecodeError, KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
            raise TakeFormatError(f"{where}: /: attr {FINALIZE_PLAN_ATTR} does not parse: {exc}") from exc


def _crash_point(stage: str, sensor: str, start: int) -> None:
    """No-op seam between the steps of a finalize block; tests replace it to simulate a crash."""


def _append(ds: h5py.Dataset, start: int, data: NDArray[Any]) -> None:
    end = start + data.shape[0]
    if ds.shape[0] < end:
        ds.resize((end, *ds.shape[1:]))
    ds[start:end] = data


#: A column's rewrite in one finalize block: [(start, stop) segments], their rows concatenated.
_Segments = tuple[list[tuple[int, int]], NDArray[Any]]


def _store_segments(ds: h5py.Dataset, segments: list[tuple[int, int]], rows: NDArray[Any]) -> None:
    pos = 0
    for a, b in segments:
        ds[a:b] = rows[pos : pos + b - a]
        pos += b - a


def _write_slot(ds: h5py.Dataset, slot: int, start: int, data: NDArray[Any]) -> None:
    ds[slot, start : start + data.shape[0]] = data


def utc_now(timespec: str = "seconds") -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec=timespec)


def _text(value: Any) -> str:
    return value.decode("utf-8") if isinstance(value, bytes) else str(value)


class TakeWriter:
    """Writes one take file; see docs/take-format.md for the layout it produces."""

    _pulse_ds: dict[str, h5py.Dataset]

    def __init__(
        self,
        path: str | Path,
        *,
        rig_config_json: str,
        take_id: str,
        config: WriterConfig,
        rigd_version: str,
        flush_interval_s: float | None = None,
    ) -> None:
        """Create the take. `flush_interval_s` (informational, the caller times the flushes)
        is stored so recovery can say how much a crash may have cost."""
        path = Path(path)
        try:
            json.loads(rig_config_json)
        except json.JSONDecodeError as exc:
            raise TakeError(f"{path}: rig_config_json is not valid JSON: {exc}") from exc
        if flush_interval_s is not None and not flush_interval_s > 0:
            raise TakeError(f"{path}: flush_interval_s must be positive, got {flush_interval_s}")
        try:
            # Default (earliest) file format: no superblock status flags, so a take left by a
            # crashed process opens without h5clear.
            f = h5py.File(path, "w-")
        except (OSError, FileExistsError) as exc:
            raise TakeError(f"cannot create take file {path}: {exc}") from exc
        self._attach(path, f, config, state="recording")
        f.attrs["schema"] = SCHEMA_NAME
        f.attrs["schema_version"] = SCHEMA_VERSION
        f.attrs["status"] = "recording"
        f.attrs["take_id"] = take_id
        f.attrs["created_utc"] = utc_now()
        f.attrs["rigd_version"] = rigd_version
        f.attrs["time_domain"] = "device"
        f.attrs["flush_count"] = np.int64(0)
        if flush_interval_s is not None:
            f.attrs["flush_interval_s"] = float(flush_interval_s)
        f.create_dataset(CONFIG_DATASET, data=rig_config_json, dtype=h5py.string_dtype("utf-8"))
        f.create_group(EVENTS_GROUP)
        f.create_group(FRAMES_GROUP)
        f.create_group(SYNC_GROUP)
        trig = f.create_group(TRIGGER_GROUP)
        pulses = trig.create_group("pulses")
        self._pulse_ds = {k: self._series(pulses, k, np.int64, {}) for k in PULSE_SERIES}
        f.flush()
        log.info("take %s created (%s)", self.path, take_id)

    def _attach(self, path: Path, f: h5py.File, config: WriterConfig, *, state: str) -> None:
        """State shared by a new take and a resumed one."""
        self.path = path
        self._f = f
        self._cfg = config
        self._ev_opts = compression_options(config.event_compression, shuffle=True)
        # Derived datasets written on finalize (ms_to_idx). The small per-item series (frame
        # times, triggers, pulses) are stored uncompressed: their last chunk is rewritten on
        # every flush, and only a fixed-size chunk is rewritten in place (see _write_tail).
        self._small_opts = compression_options(config.event_compression, shuffle=True)
        self._frame_opts = compression_options(config.frame_compression, shuffle=False)
        self._closed = False
        self._state = state
        self._version = SCHEMA_VERSION
        self._pulse_ds = {}
        self._pulse_parts: list[PulseBatch] = []
        self._n_pulse_buffered = 0
        self._n_pulses_written = 0
        self._pulse_stats = DeviceWriteStats("trigger")
        self._has_trigger = False
        self._events: dict[str, _EventSink] = {}
        self._cameras: dict[str, _CameraSink] = {}
        self._flush_count = 0
        self.flush_seconds_total = 0.0
        """Time spent in `flush` (with `fsync`, the wait for the disk too)."""
        self.flush_seconds_max = 0.0
        self._plan: _FinalizePlan | None = None
        self._repairs: list[Trim] = []

    # -- resume after a crash ----------------------------------------------------------
    @classmethod
    def resume(cls, path: str | Path, config: WriterConfig, *, extend_truncated: bool = False) -> TakeWriter:
        """Reopen a take whose writer died, so it can be finalized (or a cut-short finalize
        continued with `continue_finalize`).

        `check_repair` first trims what the kill left half-written (see `repairs`). A take whose
        finalize had started is never trimmed (all its data was flushed before finalize began),
        only checked. `config` gives the codecs of the datasets finalize adds. A take truncated
        by a failed write raises TakeTruncatedError unless `extend_truncated`: then the file is
        extended with a hole to the length HDF5 expects (no recorded byte changes) and whatever
        lay past the old end is trimmed as never written. Raises TakeInUseError if a live
        process holds the file, TakeFormatError (naming the file and dataset) if it is not a
        readable take.
        """
        path = Path(path)
        try:
            f = open_h5(path, "r+")
        except TakeTruncatedError as exc:
            if not extend_truncated:
                raise
            f = _extend_truncated(path, exc)
        try:
            return cls._resume_open(path, f, config)
        except BaseException:
            f.close()
            raise

    @classmethod
    def _resume_open(cls, path: Path, f: h5py.File, config: WriterConfig) -> TakeWriter:
        version = check_header(f, path)
        status = _text(f.attrs.get("status", ""))
        if status == "complete":
            raise TakeError(f"{path}: take is already complete; nothing to resume")
        plan_text = f.attrs.get(FINALIZE_PLAN_ATTR)
        plan = None if plan_text is None else _FinalizePlan.from_json(_text(plan_text), str(path))
        if plan is None:
            repairs = check_repair(f, path, apply=True)
            if TRUNCATED_EOF_ATTR in f.attrs:  # nothing past the old end is referenced any more
                del f.attrs[TRUNCATED_EOF_ATTR]
        else:
            # t is part rig, part device time now: only lengths can be checked, not order.
            repairs = check_repair(f, path, apply=False, check_order=False)
            if repairs:
                what = "; ".join(f"{t.hpath}: {t.reason}" for t in repairs)
                raise TakeFormatError(
                    f"{path}: finalize had started, yet the data is inconsistent ({what}); "
                    "refusing to touch it"
                )
            repairs = []
        w = cls.__new__(cls)
        w._attach(path, f, config, state="finalizing" if plan is not None else "recording")
        w._version = version
        w._repairs = repairs
        w._plan = plan
        w._flush_count = int(f.attrs.get("flush_count", 0))
        w._rebuild_sinks()
        if plan is None:
            f.flush()  # the tails check_repair merged are redundant once this is on disk
            w._drop_tails()
        if plan is not None:
            missing = [n for n in (*w._cameras, *w._events) if n not in plan.maps]
            if missing:
                raise TakeFormatError(f"{path}: /: attr {FINALIZE_PLAN_ATTR} has no clock map for {missing}")
        f.flush()
        log.info(
            "take %s resumed (%s; %d trim(s)%s)",
            path,
            status,
            len(repairs),
            ", finalize to continue" if plan is not None else "",
        )
        return w

    def _rebuild_sinks(self) -> None:
        """Writer state from what is in the file (after check_repair every group is consistent)."""
        f = self._f
        where = str(self.path)
        pulses = require_group(f, f"{TRIGGER_GROUP}/pulses", where)
        self._pulse_ds = {k: require_dataset(pulses, k, where) for k in PULSE_SERIES}
        self._n_pulses_written = int(self._pulse_ds["index"].shape[0])
        self._pulse_stats.items = self._n_pulses_written
        self._has_trigger = "info_json" in f[TRIGGER_GROUP].attrs
        for name, g in require_group(f, EVENTS_GROUP, where).items():
            ds = {k: require_dataset(g, k, where) for k in EVENT_DTYPES}
            tg = require_group(g, "trigger", where)
            trig = {
                k: require_dataset(tg, k, where) for k in TRIGGER_DTYPES if k in tg or k != "host_time_ns"
            }
            n = int(ds["t"].shape[0])
            missing = [k for k in ("width", "height") if k not in g.attrs]
            if missing:
                raise TakeFormatError(f"{where}: {g.name}: missing attribute(s) {missing}")
            sink = _EventSink(
                name,
                g,
                int(g.attrs["width"]),
                int(g.attrs["height"]),
                ds,
                trig,
                int(ds["t"].chunks[0]) if ds["t"].chunks else self._cfg.event_chunk,
                appendable=False,
                n_written=n,
                last_t=int(ds["t"][n - 1]) if n else None,
                n_trig_written=int(trig["t"].shape[0]),
            )
            sink.stats.items = n
            self._events[name] = sink
        for name, g in require_group(f, FRAMES_GROUP, where).items():
            images = require_dataset(g, "images", where)
            series = {k: require_dataset(g, k, where) for k in FRAME_SERIES}
            n = int(series["t_exposure_start_us"].shape[0])
            cam = _CameraSink(
                name,
                g,
                tuple(int(s) for s in images.shape[1:]),
                np.dtype(images.dtype),
                images,
                series,
                n_frames=n,
                n_series_written=n,
            )
            cam.stats.items = n
            self._cameras[name] = cam

    @property
    def repairs(self) -> list[Trim]:
        """What `resume` trimmed (empty for a new take or an undamaged one)."""
        return list(self._repairs)

    @property
    def finalize_pending(self) -> bool:
        """A resumed take whose finalize had started: call `continue_finalize`."""
        return self._plan is not None and self._state == "finalizing"

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
        self._f.flush()  # the layout is on disk before any data: a crash keeps the devices

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
        series = {k: self._series(g, k, np.int64, {}) for k in FRAME_SERIES}
        series["t_exposure_start_us"].attrs["units"] = "us"
        self._cameras[name] = _CameraSink(name, g, shape, dt, images, series)
        self._f.flush()

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
        trig = {k: self._series(tg, k, dt, {}) for k, dt in TRIGGER_DTYPES.items()}
        self._events[name] = _EventSink(name, g, int(width), int(height), ds, trig, chunk)
        self._f.flush()

    # -- appends -----------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise TakeError(f"{self.path}: take is closed")

    def _check_writable(self) -> None:
        self._check_open()
        if self._state != "recording":
            raise TakeError(f"{self.path}: take is {self._state}; no more data can be written")

    def _sensor(self, name: str) -> _EventSink:
        self._check_writable()
        try:
            sink = self._events[name]
        except KeyError:
            raise TakeError(f"{self.path}: unknown event sensor {name!r} (add_event_sensor first)") from None
        if not sink.appendable:
            raise TakeError(f"{self.path}: a resumed take can be finalized or failed, not appended to")
        return sink

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
        if sink.n_buffered >= sink.chunk:
            self._write_events(sink, whole_chunks_only=True)

    def append_triggers(self, name: str, triggers: TriggerEvents, host_time_ns: int | None = None) -> None:
        """Buffer trigger-in edges of an event sensor (device clock).

        `host_time_ns`: host monotonic ns when the packet carrying these edges arrived (all
        edges of one packet share it); recovery matches edges to pulses with it. None: -1.
        """
        sink = self._sensor(name)
        n = len(triggers)
        if n == 0:
            return
        sink.trig_parts.append(triggers)
        sink.trig_host_parts.append(np.full(n, -1 if host_time_ns is None else int(host_time_ns), np.int64))
        sink.n_trig_buffered += n
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
            n = total - total % sink.chunk - sink.n_written
            if n <= 0:
                return
        cols: dict[str, NDArray[Any]] = {
            "x": ev.x[:n],
            "y": ev.y[:n],
            "p": (ev.p[:n] > 0).astype(np.uint8),
            "t": ev.t[:n],
        }
        # t last: a kill between the column appends leaves t no longer than x, y, p.
        for key, data in cols.items():
            _append(sink.ds[key], sink.n_written, data)
        sink.n_written += n
        rest = ev[n:]
        sink.parts = [rest] if len(rest) else []
        sink.n_buffered = len(rest)

    def _write_tail(self, sink: _EventSink) -> None:
        """Put the buffered rows past the last whole chunk in a tail slot (flush only).

        The main x, y, p, t only ever receive whole chunks while recording, each compressed
        and written once: HDF5 stores a rewritten compressed chunk at a new address and may
        hand the old one to the next allocation while the file on disk (as of the last flush)
        still points there, so a flushed partial chunk that was later completed could be lost
        to a kill. The partial rows go to `tail_<col>` instead: two fixed, unfiltered,
        contiguous slots rewritten in place. A slot is extended while the tail's first row
        stays the same; when it moves, the other slot is used, so the slot the file on disk
        refers to is never overwritten before the flush that replaces it completes.
        """
        n = sink.n_buffered
        start = sink.n_written
        meta = sink.tail_meta
        slot = sink.tail_slot
        if n == 0 or sink.chunk <= 0:
            return
        if int(meta[slot, 0]) != start or int(meta[slot, 1]) == 0:
            slot = 1 - slot if int(meta[slot, 1]) else slot
            meta[slot] = (start, 0)
        if not sink.tail_ds:
            g = sink.group
            sink.tail_ds = {
                k: g.create_dataset(f"{TAIL_PREFIX}{k}", shape=(2, sink.chunk), dtype=dt, fillvalue=0)
                for k, dt in EVENT_DTYPES.items()
            }
        ev = EventArray.concatenate(sink.parts)
        have = int(meta[slot, 1])
        cols: dict[str, NDArray[Any]] = {
            "x": ev.x[have:n],
            "y": ev.y[have:n],
            "p": (ev.p[have:n] > 0).astype(np.uint8),
            "t": ev.t[have:n],
        }
        for key, data in cols.items():
            _write_slot(sink.tail_ds[key], slot, have, data)
        meta[slot, 1] = n
        sink.tail_slot = slot
        sink.group.attrs.modify(TAIL_META_ATTR, meta)

    def _drop_tails_after_flush(self) -> None:
        self._f.flush()  # the tails are redundant only once the main data is on disk
        self._drop_tails()

    def _discard_pending(self) -> None:
        """Point the file descriptor at /dev/null so HDF5 can close a file it failed to write.

        After a failed write HDF5 still holds dirty data it cannot write; closing then fails,
        and freeing the file's objects crashes the process (HDF5 2.0). Writes to /dev/null
        succeed, so the close completes, the lock is released, and the file on disk stays
        exactly as the failure left it (recovery repairs and seals it).
        """
        fd = int(self._f.id.get_vfd_handle())
        null = os.open(os.devnull, os.O_RDWR)
        try:
            os.dup2(null, fd)
        finally:
            os.close(null)
        log.error(
            "take %s: writes HDF5 could not complete were discarded; the file stays as last flushed",
            self.path,
        )

    def _drop_tails(self) -> None:
        """After everything is in the main datasets (close, fail, finalize) the tails go."""
        for sink in self._events.values():
            g = sink.group
            for key in EVENT_DTYPES:
                if f"{TAIL_PREFIX}{key}" in g:
                    del g[f"{TAIL_PREFIX}{key}"]
            if TAIL_META_ATTR in g.attrs:
                del g.attrs[TAIL_META_ATTR]
            sink.tail_ds = {}
            sink.tail_meta[:] = 0

    def _write_triggers(self, sink: _EventSink) -> None:
        if not sink.n_trig_buffered:
            return
        tr = TriggerEvents.concatenate(sink.trig_parts)
        host = np.concatenate(sink.trig_host_parts)
        start = sink.n_trig_written
        cols: list[tuple[str, NDArray[Any]]] = [
            ("t", tr.t),
            ("t_device", tr.t),
            ("p", tr.p),
            ("channel", tr.channel),
            ("host_time_ns", host),
        ]
        for key, data in cols:
            if key in sink.trig:  # a resumed 1.0 take has no host_time_ns
                _append(sink.trig[key], start, data)
        sink.n_trig_written += len(tr)
        sink.trig_parts, sink.trig_host_parts, sink.n_trig_buffered = [], [], 0

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

    def _write_all(self, *, final: bool = True) -> None:
        """Write every buffer: events up to the last whole chunk and the rest to their tail
        (a flush), or all of it to the main datasets (`final`: close, fail, finalize)."""
        for sink in self._events.values():
            self._write_events(sink, whole_chunks_only=not final)
            if not final:
                self._write_tail(sink)
            self._write_triggers(sink)
        for cam in self._cameras.values():
            self._write_camera(cam)
            self._trim_camera(cam)
        self._write_pulses()

    def flush(self, journal: Mapping[str, Any] | None = None) -> None:
        """Write every buffer and flush HDF5, so a crash from here on loses nothing written.

        `journal` (JSON-serialisable: the caller's losses, device counters, failed devices,
        trigger link counters, warnings) replaces `/journal_json`, so a crash does not lose the
        loss bookkeeping; recovery merges it into the sync report. Also bumps the root attrs
        `flush_count` and `last_flush_utc`. Cheap: buffered data is written once; partial
        event chunks are rewritten later.
        """
        self._check_open()
        t0 = time.perf_counter()
        n = self._flush_count + 1
        blob = None
        if journal is not None:
            try:
                blob = encode_journal(n, journal)
            except (TypeError, ValueError) as exc:
                raise TakeError(f"{self.path}: flush journal is not JSON-serialisable: {exc}") from exc
        try:
            if self._state == "recording":
                self._write_all(final=False)
            f = self._f
            if blob is not None:
                self._write_journal(blob, n)
            # Fixed-size values rewritten in place in the root object header (no heap churn).
            f.attrs.modify("flush_count", np.int64(n))
            f.attrs.modify("last_flush_utc", np.bytes_(utc_now("milliseconds")))
            f.flush()
            if self._cfg.fsync:
                os.fsync(f.id.get_vfd_handle())
        except RuntimeError as exc:
            raise _as_oserror(exc) from exc
        self._flush_count = n
        took = time.perf_counter() - t0
        self.flush_seconds_total += took
        self.flush_seconds_max = max(self.flush_seconds_max, took)

    def _write_journal(self, blob: bytes, n: int) -> None:
        """Overwrite the older of the two slots in place; the newer survives a torn write."""
        f = self._f
        node = f.get(JOURNAL_DATASET)
        if node is None or node.shape[1] < len(blob):
            cap = max(_JOURNAL_MIN_BYTES, 1 << (2 * len(blob) - 1).bit_length())
            old = np.zeros((2, 0), np.uint8) if node is None else node[...]
            if node is not None:
                del f[JOURNAL_DATASET]
            # Contiguous and unfiltered: every later write lands on the same bytes.
            node = f.create_dataset(JOURNAL_DATASET, shape=(2, cap), dtype=np.uint8, fillvalue=0)
            node[:, : old.shape[1]] = old
        row = np.zeros(node.shape[1], np.uint8)
        row[: len(blob)] = np.frombuffer(blob, np.uint8)
        node[n % 2] = row

    # -- finalize ----------------------------------------------------------------------
    def finalize(
        self,
        maps: dict[str, ClockMap],
        frame_pulse_index: dict[str, NDArray[np.int64]],
        report: SyncReport,
    ) -> None:
        """Map every stored time to rig time, build the DSEC index and mark the take complete.

        Crash-safe: the maps and t_offset are stored first (`finalize_plan_json`), then each
        block of event times goes through a redo log and a progress attr, so a take whose
        process died here is finished by `resume` + `continue_finalize` with identical times.
        """
        if self._plan is not None:
            raise TakeError(f"{self.path}: finalize already started; call continue_finalize()")
        self._check_writable()
        self._write_all()
        self._drop_tails()
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
        plan = _FinalizePlan(t_offset, source, dict(maps))
        f = self._f
        # Idempotent parts first; none of them touches a device time.
        for name, idx in frame_pulse_index.items():
            self._cameras[name].series["pulse_index"][...] = np.asarray(idx, dtype=np.int64)
        self._write_sync(plan.maps, report)
        for sink in self._events.values():
            sink.group.attrs[FINALIZE_UPTO_ATTR] = np.int64(0)
        f.attrs[FINALIZE_PLAN_ATTR] = plan.to_json()
        # If the process dies while times are being rewritten, this says so (see the docs).
        f.attrs["finalize_started_utc"] = utc_now()
        f.flush()
        self._plan = plan
        self._state = "finalizing"
        self._run_finalize(plan)

    def continue_finalize(self, report: SyncReport | None = None) -> None:
        """Finish a finalize that a crash cut short, with the maps and t_offset it started with.

        `report` replaces the stored sync report (recovery adds its notes); the mapping never
        changes, so the result is the same as an uninterrupted finalize.
        """
        self._check_open()
        if self._plan is None or self._state != "finalizing":
            raise TakeError(f"{self.path}: no interrupted finalize to continue (status {self._state})")
        if report is not None:
            self._write_sync(self._plan.maps, report)
        self._run_finalize(self._plan)

    def _run_finalize(self, plan: _FinalizePlan) -> None:
        f = self._f
        for name, sink in self._events.items():
            self._finalize_events(sink, plan.maps[name], plan.t_offset)
            sink.group.attrs["t_offset_source"] = plan.source
        for name, cam in self._cameras.items():
            dev = cam.series["t_exposure_start_device_us"][...]
            cam.series["t_exposure_start_us"][...] = plan.maps[name].to_rig(dev)
        f.attrs["time_domain"] = "rig"
        f.attrs["status"] = "complete"
        if "finalize_started_utc" in f.attrs:
            del f.attrs["finalize_started_utc"]
        f.attrs["finalized_utc"] = utc_now()
        f.flush()
        self._state = "complete"
        # Bookkeeping goes only after "complete" is on disk: dropping t_rig_upto earlier could
        # make a resumed finalize map the events a second time.
        for sink in self._events.values():
            g = sink.group
            if FINALIZE_UPTO_ATTR in g.attrs:
                del g.attrs[FINALIZE_UPTO_ATTR]
            if FINALIZE_SCRATCH in g:
                del g[FINALIZE_SCRATCH]
        self._drop_tails()
        if FINALIZE_PLAN_ATTR in f.attrs:
            del f.attrs[FINALIZE_PLAN_ATTR]
        f.flush()
        log.info("take %s finalized (t_offset %d us)", self.path, plan.t_offset)

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
        """Rewrite t as rig time - t_offset block by block and build ms_to_idx on the way.

        Events [0, t_rig_upto) are already rewritten (a resumed finalize): they are only read
        for ms_to_idx. A block logged in the scratch dataset but not confirmed is copied from
        there, never mapped again from a `t` the crash may have left half rewritten.
        """
        g = sink.group
        tds = sink.ds["t"]
        n = sink.n_written
        upto = min(int(g.attrs.get(FINALIZE_UPTO_ATTR, 0)), n)
        block = max(sink.chunk, _FINALIZE_BLOCK // sink.chunk * sink.chunk)
        upto = self._redo_logged_block(sink, upto)
        if n == 0:
            last_rel = -1
        elif upto >= n:
            last_rel = int(tds[n - 1])
        else:
            last_rel = int(cmap.to_rig(tds[n - 1 : n])[0]) - t_offset
        n_ms = last_rel // 1000 + 1 if last_rel >= 0 else 0
        if "ms_to_idx" in g:
            # Derived: rebuilt whole, so no chunk a crashed finalize left behind is ever read.
            del g["ms_to_idx"]
        ms_ds = g.create_dataset(
            "ms_to_idx",
            shape=(n_ms,),
            dtype=np.uint64,
            chunks=(min(max(n_ms, 1), 1 << 16),),
            **self._small_opts,
        )
        ms_next = 0
        pos = 0
        while pos < n:
            if pos < upto:
                stop = min(pos + block, upto)
                rel: NDArray[np.int64] = np.asarray(tds[pos:stop], dtype=np.int64)
            else:
                stop = min(pos + block, n)
                rel = cmap.to_rig(tds[pos:stop]) - t_offset
                self._rewrite_block(sink, pos, stop, {"t": ([(pos, stop)], rel)})
            ms_hi = min(int(rel[-1]) // 1000 + 1, n_ms) if rel[-1] >= 0 else 0
            while ms_next < ms_hi:
                step_hi = min(ms_next + _MS_STEP, ms_hi)
                thresholds = np.arange(ms_next, step_hi, dtype=np.int64) * 1000
                ms_ds[ms_next:step_hi] = (np.searchsorted(rel, thresholds, side="left") + pos).astype(
                    np.uint64
                )
                ms_next = step_hi
            pos = stop
        g["t_offset"][()] = np.int64(t_offset)
        trig_dev = sink.trig["t_device"][...]
        sink.trig["t"][...] = cmap.to_rig(trig_dev)

    def _rewrite_block(self, sink: _EventSink, start: int, stop: int, writes: dict[str, _Segments]) -> None:
        """Redo-logged in-place rewrite of one block: log, mark, write, confirm.

        `writes`: per column, the rows to store at its segments (t: the mapped block; x, y, p:
        chunks still stored raw, recompressed). Each step is flushed before the next, so
        whatever a kill leaves on disk is the old block with a stale log, a complete log to
        copy from, or the confirmed new block: nothing is ever mapped twice.
        """
        g = sink.group
        log_g = g.get(FINALIZE_SCRATCH)
        if log_g is None:
            log_g = g.create_group(FINALIZE_SCRATCH)
        for key in list(log_g):
            if key not in writes:
                del log_g[key]
        for key, (segments, rows) in writes.items():
            ds = log_g.get(key)
            if ds is None:
                # Compressed like the events: a rewritten log moves, but the log that is
                # current on disk is never freed before the block it covers is confirmed.
                ds = log_g.create_dataset(
                    key,
                    shape=(rows.shape[0],),
                    maxshape=(None,),
                    dtype=rows.dtype,
                    chunks=(max(1, min(rows.shape[0], 1 << 20)),),
                    **self._ev_opts,
                )
            else:
                ds.resize((rows.shape[0],))
            ds[...] = rows
            ds.attrs["segments"] = np.asarray(segments, dtype=np.int64).reshape(-1, 2)
        _crash_point("scratch_written", sink.name, start)
        self._f.flush()
        log_g.attrs.modify("range", np.array([start, stop], dtype=np.int64))
        self._f.flush()
        _crash_point("scratch_logged", sink.name, start)
        for key, (segments, rows) in writes.items():
            _store_segments(sink.ds[key], segments, rows)
        _crash_point("t_written", sink.name, start)
        g.attrs.modify(FINALIZE_UPTO_ATTR, np.int64(stop))
        self._f.flush()

    def _redo_logged_block(self, sink: _EventSink, upto: int) -> int:
        """Copy a logged, unconfirmed block from the redo log; returns the new t_rig_upto."""
        g = sink.group
        log_g = g.get(FINALIZE_SCRATCH)
        if not isinstance(log_g, h5py.Group) or "range" not in log_g.attrs:
            return upto
        lo, hi = (int(v) for v in log_g.attrs["range"])
        if not (lo == upto and upto < hi <= sink.n_written):
            return upto  # stale: that block was confirmed
        log.info("take %s: %s: redoing finalize block [%d, %d) from its log", self.path, sink.name, lo, hi)
        for key, ds in log_g.items():
            segments = [(int(a), int(b)) for a, b in np.asarray(ds.attrs["segments"]).reshape(-1, 2)]
            _store_segments(sink.ds[key], segments, np.asarray(ds[...]))
        g.attrs.modify(FINALIZE_UPTO_ATTR, np.int64(hi))
        self._f.flush()
        return hi

    def _write_sync(self, maps: Mapping[str, ClockMap], report: SyncReport) -> None:
        """(Re)write /sync; replacing it is safe, it holds no recorded data."""
        sync = self._f[SYNC_GROUP]
        for key in ("report_json", "devices"):
            if key in sync:
                del sync[key]
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
    def mark_recovered(self, recovery_report_json: str | None) -> None:
        """Stamp a take sealed by recovery (`recovered_utc`, and the report once known).

        A take that a crashed finalize had marked failed and that is now complete drops its
        stale `failure_reason`; the recovery report keeps it.
        """
        self._check_open()
        f = self._f
        if RECOVERED_ATTR not in f.attrs:
            f.attrs[RECOVERED_ATTR] = utc_now()
        if recovery_report_json is not None:
            f.attrs[RECOVERY_REPORT_ATTR] = recovery_report_json
        if self._state == "complete" and "failure_reason" in f.attrs:
            del f.attrs["failure_reason"]
        f.flush()

    def fail(self, reason: str) -> None:
        """Mark the take failed with a reason; everything written so far stays readable.

        A write that fails here (disk full) does not stop the status from being set; it is
        raised afterwards as OSError.
        """
        self._check_open()
        if self._state == "complete":
            log.warning("take %s: fail(%r) after finalize ignored", self.path, reason)
            return
        error: BaseException | None = None
        try:
            if self._state == "recording":
                self._write_all()
                self._drop_tails_after_flush()
        except (OSError, RuntimeError) as exc:
            error = exc
        self._state = "failed"
        try:
            self._f.attrs["status"] = "failed"
            self._f.attrs["failure_reason"] = reason
            self._f.flush()
        except (OSError, RuntimeError) as exc:
            error = error or exc
        log.error("take %s marked failed: %s", self.path, reason)
        if error is not None:
            raise _as_oserror(error) from error

    def close(self) -> None:
        """Write buffers and close. Idempotent; an unfinalized take stays "recording".

        Raises OSError if a write fails (disk full). The file is closed all the same, with what
        HDF5 could not write discarded (see _discard_pending): it stays as last flushed, for
        `rigd recover`, and its lock is released.
        """
        if self._closed:
            return
        error: BaseException | None = None
        try:
            if self._state == "recording":
                self._write_all()
                self._drop_tails_after_flush()
            else:
                self._f.flush()
        except (OSError, RuntimeError) as exc:
            error = exc
        self._closed = True
        try:
            if error is not None:
                self._discard_pending()
            elif self._cfg.fsync:
                self._f.flush()
                os.fsync(self._f.id.get_vfd_handle())
            self._f.close()
            if error is None and self._cfg.fsync:
                fsync_dir(self.path.parent)  # the file's directory entry, for a new take
        except (OSError, RuntimeError) as exc:
            error = error or exc
            _UNCLOSABLE.append(self)
            log.error("take %s could not be closed (%s); its handle is kept until exit", self.path, exc)
        log.info("take %s closed (%s)", self.path, self._state)
        if error is not None:
            raise _as_oserror(error) from error

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def set_end_reason(self, reason: str) -> None:
        """Why the recording ended (pulses done, an operator's stop, a fault), for whoever
        reads the take later."""
        self._check_writable()
        self._f.attrs[END_REASON_ATTR] = reason

    @property
    def flush_count(self) -> int:
        return self._flush_count

    @property
    def status(self) -> str:
        return self._state

    @property
    def schema_version(self) -> str:
        """Of the file: a resumed take keeps the version it was written with."""
        return self._version

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


# -- opening, checking and repairing a take left by a dead writer --------------------------
def _extend_truncated(path: Path, exc: TakeTruncatedError) -> h5py.File:
    """Give a truncated take the length its superblock records (a sparse hole, no disk space
    needed) and note the real end, so check_repair treats what lay past it as never written."""
    size = path.stat().st_size
    if size != exc.eof or exc.stored_eof <= exc.eof:
        raise TakeFormatError(f"{path}: changed while being recovered (size {size}, expected {exc.eof})")
    log.warning(
        "take %s is %d bytes short of what its header records (a write failed); extending it with a hole",
        path,
        exc.stored_eof - exc.eof,
    )
    os.truncate(path, exc.stored_eof)
    f = open_h5(path, "r+")
    f.attrs[TRUNCATED_EOF_ATTR] = np.int64(exc.eof)
    f.flush()
    return f


class ZeroPadded(io.RawIOBase):
    """Read-only view of a truncated file, zeros past its end up to `size`: lets h5py open a
    take a failed write left short without changing a byte of it (dry runs)."""

    def __init__(self, path: Path, size: int) -> None:
        super().__init__()
        self._f = path.open("rb")
        self._real = os.fstat(self._f.fileno()).st_size
        self._size = size
        self._pos = 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self._pos, io.SEEK_END: self._size}[whence]
        self._pos = base + offset
        return self._pos

    def tell(self) -> int:
        return self._pos

    def readinto(self, buf: Any) -> int:
        view = memoryview(buf).cast("B")
        n = max(0, min(len(view), self._size - self._pos))
        got = 0
        if self._pos < self._real:
            self._f.seek(self._pos)
            got = self._f.readinto(view[: min(n, self._real - self._pos)]) or 0
        view[got:n] = bytes(n - got)
        self._pos += n
        return n

    def close(self) -> None:
        self._f.close()
        super().close()


def fsync_dir(directory: Path) -> None:
    """Make a new file's name durable (POSIX: fsync the directory that holds it)."""
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def is_lock_error(exc: OSError) -> bool:
    """Whether h5py refused to open a file because another process holds its HDF5 lock."""
    return isinstance(exc, BlockingIOError) or "errno = 11," in str(exc)


def open_h5(path: Path, mode: str) -> h5py.File:
    """Open with HDF5 file locking on, so a take a live writer holds is never opened
    (best-effort: file systems without locks open anyway)."""
    if not path.is_file():
        raise TakeError(f"{path}: no such take file")
    try:
        return h5py.File(path, mode, locking="best-effort")
    except OSError as exc:
        if is_lock_error(exc):
            raise TakeInUseError(
                f"{path}: in use: another process has it open for writing (HDF5 file lock)"
            ) from exc
        m = _TRUNCATED_RE.search(str(exc))
        if m:
            eof, stored = int(m.group(1)), int(m.group(2))
            raise TakeTruncatedError(
                f"{path}: truncated by a failed write (disk full?): the file ends at byte {eof}, its "
                f"header records {stored}; `rigd recover` extends it and trims what was never written",
                eof,
                stored,
            ) from exc
        raise TakeFormatError(f"{path}: cannot be opened as an HDF5 file: {exc}") from exc


def check_header(f: h5py.File, path: Path) -> str:
    """Schema name and major version of an open take; returns its schema_version."""
    schema = _text(f.attrs.get("schema", ""))
    if schema != SCHEMA_NAME:
        raise TakeFormatError(f"{path}: /: attr schema is {schema!r}, expected {SCHEMA_NAME!r}")
    version = _text(f.attrs.get("schema_version", ""))
    if version.split(".")[0] != SCHEMA_VERSION.split(".")[0]:
        raise TakeFormatError(
            f"{path}: /: schema_version {version!r} is not readable by this rigd "
            f"(reads {SCHEMA_VERSION.split('.')[0]}.x)"
        )
    return version


def require_group(parent: h5py.Group, name: str, where: str) -> h5py.Group:
    node = parent.get(name)
    if not isinstance(node, h5py.Group):
        raise TakeFormatError(f"{where}: {parent.name.rstrip('/')}/{name} is missing or not a group")
    return node


def require_dataset(parent: h5py.Group, name: str, where: str) -> h5py.Dataset:
    node = parent.get(name)
    if not isinstance(node, h5py.Dataset):
        raise TakeFormatError(f"{where}: {parent.name.rstrip('/')}/{name} is missing or not a dataset")
    return node


def stored_prefix(ds: h5py.Dataset, data_end: int | None = None) -> int:
    """Leading entries of a chunked dataset whose chunks were all written.

    Its extent can run ahead of its chunks when a kill interrupted a flush: entries past the
    first missing chunk would silently read as the fill value (zeros). With `data_end` (the
    real end of a truncated file) a chunk stored past it counts as missing too.
    """
    n = int(ds.shape[0]) if ds.shape else 0
    if n == 0 or ds.chunks is None:
        return n
    step = int(ds.chunks[0])
    have = np.zeros(-(-n // step), dtype=bool)

    def seen(info: Any) -> None:
        i = int(info.chunk_offset[0]) // step
        if i < have.size and (data_end is None or int(info.byte_offset) + int(info.size) <= data_end):
            have[i] = True

    _chunk_iter(ds, seen)
    missing = np.flatnonzero(~have)
    return n if missing.size == 0 else int(missing[0]) * step


def _columns_keep(
    cols: Mapping[str, h5py.Dataset],
    data_end: int | None,
    nonzero: tuple[str, ...],
    order: tuple[str, str] | None,
    what: str,
) -> tuple[int, int, list[str]]:
    """For a group of parallel columns: their longest length, the rows to keep (stored in every
    column and not a stale zero tail) and why any are cut."""
    longest = max(int(d.shape[0]) for d in cols.values())
    stored = min(stored_prefix(d, data_end) for d in cols.values())
    keep = _stale_tail(cols, stored, nonzero, order)
    reasons = [f"{what} columns of unequal or unwritten length"] if stored < longest else []
    if keep < stored:
        reasons.append("zero-filled tail (a chunk the interrupted flush did not update)")
    return longest, keep, reasons


def _stale_tail(
    dsets: Mapping[str, h5py.Dataset], n: int, nonzero: tuple[str, ...], same: tuple[str, str] | None
) -> int:
    """Rows [0, n) less a tail that a chunk the interrupted flush did not update reads as 0.

    Columns are append-only, so such a chunk (its B-tree entry still names the previous
    version while the extent already covers the new rows) reads as the correct prefix followed
    by the fill value 0. `nonzero` columns never hold 0 after a nonzero value in real data
    (host times, device clocks); a column that is all zeros says nothing and is skipped.
    `same`: two columns the writer stores identical while recording (t and its device copy).
    """
    keep = n
    for key in nonzero:
        last = _last_nonzero(dsets[key], keep)
        if last > 0:
            keep = last
    if same is not None:
        keep = _first_mismatch(dsets[same[0]], dsets[same[1]], keep)
    return keep


def _last_nonzero(ds: h5py.Dataset, n: int) -> int:
    """1 + index of the last nonzero entry in ds[:n] (0 if none), scanning back in blocks."""
    hi = n
    while hi > 0:
        lo = max(0, hi - _SCAN_BLOCK)
        hit = np.flatnonzero(np.asarray(ds[lo:hi]) != 0)
        if hit.size:
            return lo + int(hit[-1]) + 1
        hi = lo
    return 0


def _first_mismatch(a: h5py.Dataset, b: h5py.Dataset, n: int) -> int:
    """First index i < n with a[i] != b[i], else n (forward, in blocks)."""
    for lo in range(0, n, _SCAN_BLOCK):
        hi = min(lo + _SCAN_BLOCK, n)
        bad = np.flatnonzero(np.asarray(a[lo:hi]) != np.asarray(b[lo:hi]))
        if bad.size:
            return lo + int(bad[0])
    return n


def _first_decrease(ds: h5py.Dataset, n: int) -> int | None:
    """First index i < n with ds[i] < ds[i-1], scanning in blocks (constant memory)."""
    prev: int | None = None
    for start in range(0, n, _SCAN_BLOCK):
        t = np.asarray(ds[start : min(start + _SCAN_BLOCK, n)], dtype=np.int64)
        if prev is not None and int(t[0]) < prev:
            return start
        bad = np.flatnonzero(t[1:] < t[:-1])
        if bad.size:
            return start + int(bad[0]) + 1
        prev = int(t[-1])
    return None


def tail_rows(g: h5py.Group, main_len: int) -> tuple[int, int]:
    """(slot, rows) of the flushed tail that continues the main event datasets at `main_len`;
    rows = 0 when no slot starts there (no tail, or the rows it held are in main already).

    A slot is only used if its `t` continues the main `t` without decreasing.
    """
    meta = np.asarray(g.attrs.get(TAIL_META_ATTR, np.zeros((2, 2))), dtype=np.int64).reshape(-1, 2)
    t_ds = g.get(f"{TAIL_PREFIX}t")
    if not isinstance(t_ds, h5py.Dataset) or meta.shape[0] != t_ds.shape[0]:
        return 0, 0
    best = (0, 0)
    for slot, (start, n) in enumerate(meta):
        n = min(int(n), int(t_ds.shape[1]))
        if int(start) != main_len or n <= best[1]:
            continue
        t = np.asarray(t_ds[slot, :n], dtype=np.int64)
        prev = int(g["t"][main_len - 1]) if main_len else None
        if (prev is not None and int(t[0]) < prev) or bool((t[1:] < t[:-1]).any()):
            continue
        best = (slot, n)
    return best


def _tail_beyond(g: h5py.Group) -> int:
    """Last row + 1 any tail slot claims (0 without tails)."""
    meta = np.asarray(g.attrs.get(TAIL_META_ATTR, np.zeros((2, 2))), dtype=np.int64).reshape(-1, 2)
    return int((meta[:, 0] + meta[:, 1]).max(initial=0)) if (meta[:, 1] > 0).any() else 0


def _trim_group(
    trims: list[Trim],
    group: h5py.Group,
    dsets: Mapping[str, h5py.Dataset],
    keep: int,
    reasons: list[str],
    device: str,
    what: LossKind,
    lost: int,
    *,
    apply: bool,
) -> None:
    lengths = {k: int(d.shape[0]) for k, d in dsets.items()}
    if all(v == keep for v in lengths.values()):
        return
    trims.append(
        Trim(
            hpath=group.name,
            lengths_before=lengths,
            after=keep,
            reason="; ".join(reasons) or "datasets of unequal length",
            device=device,
            what=what,
            lost=lost,
        )
    )
    if apply:
        for d in dsets.values():
            if d.shape[0] != keep:
                try:
                    d.resize((keep, *d.shape[1:]))
                except (OSError, RuntimeError, ValueError) as exc:
                    raise TakeFormatError(f"{d.file.filename}: {d.name}: cannot be trimmed: {exc}") from exc


def check_repair(
    f: h5py.File, path: Path, *, apply: bool, check_order: bool = True, data_end: int | None = None
) -> list[Trim]:
    """Find (and with `apply`, trim) what a writer killed between flushes left half-written.

    Per group, every dataset is cut to the length all of them really hold: event columns to
    their common stored length and before a non-monotonic tail of `t` (the writer only ever
    stores non-decreasing t, so a decrease is damage); camera images to the flushed timestamp
    series (the rest is preallocation or frames whose timestamps were lost); trigger-in and
    pulse columns to their common stored length; and everywhere a zero-filled tail a stale chunk
    leaves (see `_stale_tail`). Nothing is ever cut silently: each cut is a
    `Trim`, with how many items of real data it lost. `check_order=False` skips the scan of
    `t` (a finalize in progress has rewritten part of it). `data_end`: where a truncated file
    really ends (default: the `truncated_eof` attr resume leaves on an extended one).
    """
    at = ["/"]  # the group being checked, for the message of a read error
    try:
        return _check_repair(f, path, apply, check_order, data_end, at)
    except (OSError, RuntimeError) as exc:
        raise TakeFormatError(f"{path}: {at[0]}: cannot be read: {exc}") from exc


def _check_repair(
    f: h5py.File, path: Path, apply: bool, check_order: bool, data_end: int | None, at: list[str]
) -> list[Trim]:
    where = str(path)
    if data_end is None and TRUNCATED_EOF_ATTR in f.attrs:
        data_end = int(f.attrs[TRUNCATED_EOF_ATTR])
    version = _text(f.attrs.get("schema_version", SCHEMA_VERSION))
    trims: list[Trim] = []
    for name, g in require_group(f, EVENTS_GROUP, where).items():
        at[0] = g.name
        cols = {k: require_dataset(g, k, where) for k in EVENT_DTYPES}
        longest = max(int(d.shape[0]) for d in cols.values())
        stored_ev = {k: stored_prefix(d, data_end) for k, d in cols.items()}
        keep = min(stored_ev.values())
        reasons = []
        if len({int(d.shape[0]) for d in cols.values()}) > 1:
            reasons.append("x/y/p/t of unequal length (killed between column appends)")
        if any(stored_ev[k] < int(cols[k].shape[0]) for k in cols):
            reasons.append("chunks past the end never reached the file")
        bad = _first_decrease(cols["t"], keep) if check_order else None
        if bad is not None:
            reasons.append(f"t decreases at index {bad} (damaged tail)")
            keep = bad
        _trim_group(trims, g, cols, keep, reasons, name, "events", longest - keep, apply=apply)
        # The flushed rows past the last whole chunk (see TakeWriter._write_tail).
        slot, m = tail_rows(g, keep) if check_order else (0, 0)
        beyond = _tail_beyond(g) - max(longest, keep + m)
        if beyond > 0:
            trims.append(
                Trim(
                    hpath=f"{g.name}/{TAIL_PREFIX}t",
                    lengths_before={"rows_claimed": _tail_beyond(g)},
                    after=keep + m,
                    reason="flushed tail events that do not continue the main datasets (gap or damage)",
                    device=name,
                    what="events",
                    lost=beyond,
                )
            )
        if apply and m:
            for key, d in cols.items():  # a new chunk: appended, nothing rewritten
                _append(d, keep, np.asarray(g[f"{TAIL_PREFIX}{key}"][slot, :m]))
        tg = require_group(g, "trigger", where)
        at[0] = tg.name
        # host_time_ns is required from schema 1.1 on and used whenever present.
        keys = [
            k
            for k in TRIGGER_DTYPES
            if k != "host_time_ns" or k in tg or has_item(version, "trigger/host_time_ns")
        ]
        trig = {k: require_dataset(tg, k, where) for k in keys}
        nonzero = ("t_device", "host_time_ns") if "host_time_ns" in trig else ("t_device",)
        order = ("t", "t_device") if check_order else None
        longest, keep, reasons = _columns_keep(trig, data_end, nonzero, order, "trigger")
        _trim_group(
            trims,
            tg,
            trig,
            keep,
            reasons,
            name,
            "triggers",
            longest - keep,
            apply=apply,
        )
    for name, g in require_group(f, FRAMES_GROUP, where).items():
        at[0] = g.name
        series = {k: require_dataset(g, k, where) for k in FRAME_SERIES}
        images = require_dataset(g, "images", where)
        n_series = max(int(d.shape[0]) for d in series.values())
        stored = min(stored_prefix(d, data_end) for d in series.values())
        reasons = []
        if stored < n_series:
            reasons.append("timestamp series of unequal or unwritten length")
        keep = _stale_tail(
            series,
            stored,
            ("t_exposure_start_device_us", "host_time_ns"),
            ("t_exposure_start_us", "t_exposure_start_device_us") if check_order else None,
        )
        if keep < stored:
            reasons.append("zero-filled tail of the timestamp series (a chunk the flush did not update)")
        img_stored = stored_prefix(images, data_end)
        n_img = int(images.shape[0])
        if img_stored < keep:
            reasons.append("images past the end never reached the file")
            keep = img_stored
        if n_img > keep:
            reasons.append(f"images beyond the {keep} flushed timestamps (preallocation, frames not flushed)")
        # Frames beyond `keep` whose image was stored are real frames that lost their timestamps.
        stored_imgs = _allocated_chunks(images, data_end)
        lost = max(n_series - keep, int((stored_imgs >= keep).sum()))
        _trim_group(trims, g, {"images": images, **series}, keep, reasons, name, "frames", lost, apply=apply)
    pulses = require_group(f, f"{TRIGGER_GROUP}/pulses", where)
    at[0] = pulses.name
    cols = {k: require_dataset(pulses, k, where) for k in PULSE_SERIES}
    longest, keep, reasons = _columns_keep(cols, data_end, ("index", "t_us", "host_time_ns"), None, "pulse")
    _trim_group(
        trims,
        pulses,
        cols,
        keep,
        reasons,
        "trigger",
        "pulses",
        longest - keep,
        apply=apply,
    )
    for t in trims:
        log.warning(
            "take %s: %s trimmed to %d (%s; %d item(s) of data lost)%s",
            path,
            t.hpath,
            t.after,
            t.reason,
            t.lost,
            "" if apply else " [dry run]",
        )
    return trims


def _allocated_chunks(ds: h5py.Dataset, data_end: int | None) -> NDArray[np.int64]:
    """First-axis offsets of the chunks that hold data (within the file's real end)."""
    if ds.chunks is None or not ds.shape or ds.shape[0] == 0:
        return np.empty(0, np.int64)
    offsets: list[int] = []

    def seen(info: Any) -> None:
        if data_end is None or int(info.byte_offset) + int(info.size) <= data_end:
            offsets.append(int(info.chunk_offset[0]))

    _chunk_iter(ds, seen)
    return np.asarray(offsets, dtype=np.int64)


def _chunk_iter(ds: h5py.Dataset, fn: Callable[[Any], None]) -> None:
    """Call fn(StoreInfo) for every allocated chunk; one pass (H5Dchunk_iter, HDF5 >= 1.14)."""
    dsid = ds.id
    if hasattr(dsid, "chunk_iter"):
        dsid.chunk_iter(fn)
        return
    for i in range(dsid.get_num_chunks()):  # older HDF5: slower, same answer
        fn(dsid.get_chunk_info(i))
