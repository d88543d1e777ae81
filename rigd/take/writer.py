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

The writer is a front over its parts: `rigd.take.sinks` (per-device buffers and writes, with
the tail slots of `rigd.take.tails`), `rigd.take.repair` (what a kill left half-written),
`rigd.take.finalize` (the rig-time rewrite) and `rigd.take.h5file` (opening and HDF5 helpers).
The names other packages import from here are re-exported from those modules.
"""

from __future__ import annotations

import json
import logging
import os
import re
import time
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from typing import Any, Self

import h5py
import numpy as np
from numpy.typing import DTypeLike, NDArray

from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.errors import TakeError, TakeFormatError, TakeTruncatedError, WriteDeferredError
from rigd.core.events import EventArray, EventPacket, TriggerEvents
from rigd.core.frames import Frame
from rigd.core.layout import (
    EVENTS_GROUP,
    FRAMES_GROUP,
    PULSES_PATH,
    SYNC_GROUP,
    TRIGGER_GROUP,
    Device,
    Events,
    Pulses,
    Root,
    Status,
    Storage,
    TimeDomain,
)
from rigd.core.schema import SCHEMA_NAME, SCHEMA_VERSION, SyncReport, encode_journal
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.evt import FORMATS as EVT_FORMATS
from rigd.take.calibration import write_board_pose, write_calibration_group
from rigd.take.evt_sink import EvtWordsSink, is_evt_words
from rigd.take.finalize import FinalizePlan, Finalizer
from rigd.take.h5file import (
    TRUNCATED_EOF_ATTR,
    Syncer,
    ZeroPadded,
    as_oserror,
    attr_text,
    check_header,
    compression_options,
    fsync_dir,
    is_lock_error,
    open_extended,
    open_h5,
    require_dataset,
    require_group,
    utc_now,
)
from rigd.take.refused import discard_pending_writes, no_room_to_flush
from rigd.take.repair import Trim, check_repair, stored_prefix
from rigd.take.sinks import CameraSink, DeviceWriteStats, EventSink, PulseSink
from rigd.take.tails import tail_rows
from rigd.take.units import label_tree

__all__ = [
    "TRUNCATED_EOF_ATTR",
    "DeviceWriteStats",
    "TakeWriter",
    "Trim",
    "ZeroPadded",
    "check_header",
    "check_repair",
    "compression_options",
    "fsync_dir",
    "is_lock_error",
    "open_h5",
    "require_dataset",
    "require_group",
    "stored_prefix",
    "tail_rows",
    "utc_now",
]

log = logging.getLogger(__name__)

_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_-]{0,31}$")
#: Smallest journal slot; a bigger journal doubles it.
_JOURNAL_MIN_BYTES = 4096
#: Writers whose file could not be closed even with its pending writes discarded: HDF5 (2.0)
#: crashes the process when the objects of such a file are freed, so they are kept.
_UNCLOSABLE: list[TakeWriter] = []
#: Raw-data chunk cache of each dataset while writing (HDF5 2.0's default is 8 MiB): none. The
#: writer writes whole chunks (events, one frame per chunk) and appends rows once a flush, so a
#: cache only holds data back: dirty chunks that a full disk leaves nowhere to go when the take
#: is marked failed and closed (the ballast would have to cover them). Worse, HDF5 notes where a
#: cached chunk goes before writing it and indexes it only after: when that write fails (disk
#: full), the retry `fail` makes in the ballast's room writes the chunk but never indexes it, and
#: it reads back as zeros (columns storage: a whole chunk of event times, silently). Uncached,
#: a write fails at the call that made it, and its retry is indexed (tests/rigd/test_take_evt_words).
WRITE_CHUNK_CACHE_BYTES = 0


class TakeWriter:
    """Writes one take file; see docs/take-format.md for the layout it produces."""

    _pulses: PulseSink

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
            f = h5py.File(path, "w-", rdcc_nbytes=WRITE_CHUNK_CACHE_BYTES)
        except (OSError, FileExistsError) as exc:
            raise TakeError(f"cannot create take file {path}: {exc}") from exc
        self._attach(path, f, config, state="recording")
        f.attrs[Root.SCHEMA] = SCHEMA_NAME
        f.attrs[Root.SCHEMA_VERSION] = SCHEMA_VERSION
        f.attrs[Root.STATUS] = Status.RECORDING
        f.attrs[Root.TAKE_ID] = take_id
        f.attrs[Root.CREATED_UTC] = utc_now()
        f.attrs[Root.RIGD_VERSION] = rigd_version
        f.attrs[Root.TIME_DOMAIN] = TimeDomain.DEVICE
        f.attrs[Root.FLUSH_COUNT] = np.int64(0)
        if flush_interval_s is not None:
            f.attrs[Root.FLUSH_INTERVAL_S] = float(flush_interval_s)
        f.create_dataset(Root.CONFIG, data=rig_config_json, dtype=h5py.string_dtype("utf-8"))
        f.create_group(EVENTS_GROUP)
        f.create_group(FRAMES_GROUP)
        f.create_group(SYNC_GROUP)
        trig = f.create_group(TRIGGER_GROUP)
        self._pulses = PulseSink.create(trig.create_group(Pulses.GROUP))
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
        # every flush, and only a fixed-size chunk is rewritten in place (see rigd.take.tails).
        self._small_opts = compression_options(config.event_compression, shuffle=True)
        self._frame_opts = compression_options(config.frame_compression, shuffle=False)
        self._closed = False
        self._refused: OSError | None = None
        """What the file refused when `fail` tried to write (then `close` writes nothing)."""
        self._syncer = Syncer(self.path.name)
        self._state = state
        self._version = SCHEMA_VERSION
        self._has_trigger = False
        self._events: dict[str, EventSink | EvtWordsSink] = {}
        self._cameras: dict[str, CameraSink] = {}
        self._flush_count = 0
        self.flush_seconds_total = 0.0
        """Time spent in `flush` (with `fsync`, the wait for the disk too)."""
        self.flush_seconds_max = 0.0
        self._plan: FinalizePlan | None = None
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
            f = open_h5(path, "r+", rdcc_nbytes=WRITE_CHUNK_CACHE_BYTES)
        except TakeTruncatedError as exc:
            if not extend_truncated:
                raise
            f = open_extended(path, exc)
        try:
            return cls._resume_open(path, f, config)
        except BaseException:
            f.close()
            raise

    @classmethod
    def _resume_open(cls, path: Path, f: h5py.File, config: WriterConfig) -> TakeWriter:
        version = check_header(f, path)
        status = attr_text(f.attrs.get(Root.STATUS, ""))
        if status == "complete":
            raise TakeError(f"{path}: take is already complete; nothing to resume")
        plan_text = f.attrs.get(Root.FINALIZE_PLAN)
        plan = None if plan_text is None else FinalizePlan.from_json(attr_text(plan_text), str(path))
        repairs = _resume_repairs(f, path, plan)
        w = cls.__new__(cls)
        w._attach(path, f, config, state="finalizing" if plan is not None else "recording")
        w._version = version
        w._repairs = repairs
        w._plan = plan
        w._flush_count = int(f.attrs.get(Root.FLUSH_COUNT, 0))
        w._rebuild_sinks()
        if plan is None:
            f.flush()  # the tails check_repair merged are redundant once this is on disk
            w._drop_tails()
        if plan is not None:
            missing = [n for n in (*w._cameras, *w._events) if n not in plan.maps]
            if missing:
                raise TakeFormatError(f"{path}: /: attr {Root.FINALIZE_PLAN} has no clock map for {missing}")
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
        self._pulses = PulseSink.reopen(require_group(f, PULSES_PATH, where), where)
        self._has_trigger = Device.INFO_JSON in f[TRIGGER_GROUP].attrs
        for name, g in require_group(f, EVENTS_GROUP, where).items():
            if is_evt_words(g):
                self._events[name] = EvtWordsSink.reopen(name, g, where)
            else:
                self._events[name] = EventSink.reopen(name, g, where, self._cfg.event_chunk)
        for name, g in require_group(f, FRAMES_GROUP, where).items():
            self._cameras[name] = CameraSink.reopen(name, g, where)

    @property
    def repairs(self) -> list[Trim]:
        """What `resume` trimmed (empty for a new take or an undamaged one)."""
        return list(self._repairs)

    @property
    def finalize_pending(self) -> bool:
        """A resumed take whose finalize had started: call `continue_finalize`."""
        return self._plan is not None and self._state == "finalizing"

    # -- setup -------------------------------------------------------------------------
    def _check_new_device(self, name: str) -> None:
        self._check_writable()
        if not _NAME_RE.match(name):
            raise TakeError(
                f"{self.path}: device name {name!r} is not a valid take name ({_NAME_RE.pattern})"
            )
        if name in self._events or name in self._cameras:
            raise TakeError(f"{self.path}: device {name!r} added twice")

    def add_trigger(self, info: DeviceInfo) -> None:
        """Record the trigger box identity on `/trigger`."""
        self._check_writable()
        _write_info_attrs(self._f[TRIGGER_GROUP], info, None)
        self._has_trigger = True
        self._f.flush()  # the layout is on disk before any data: a crash keeps the devices

    def add_camera(
        self,
        name: str,
        info: DeviceInfo,
        shape: tuple[int, ...],
        dtype: DTypeLike,
        settings_json: str,
        pixel_format: str | None = None,
    ) -> None:
        """Create `/frames/<name>`; frames must then match `shape` and `dtype` exactly.
        `pixel_format` (None: mono8 or rgb8 by the shape) is what the camera sends, stored as is:
        a `bayer_rg8` camera's (H, W) mosaics are not converted while recording."""
        self._check_new_device(name)
        shape = tuple(int(s) for s in shape)
        if len(shape) not in (2, 3) or min(shape) <= 0:
            raise TakeError(f"{self.path}: camera {name!r}: frame shape {shape} is not (H, W) or (H, W, C)")
        fmt = CameraSink.check_format(pixel_format, shape, np.dtype(dtype), f"{self.path}: camera {name!r}")
        g = self._f[FRAMES_GROUP].create_group(name)
        _write_info_attrs(g, info, settings_json)
        self._cameras[name] = CameraSink.create(name, g, shape, np.dtype(dtype), self._frame_opts, fmt)
        self._f.flush()

    def add_event_sensor(
        self,
        name: str,
        info: DeviceInfo,
        width: int,
        height: int,
        settings_json: str,
        evt_format: str | None = None,
    ) -> None:
        """Create `/events/<name>` and its trigger-in group. `evt_format`: the sensor's packets
        carry the EVT words they were decoded from (`EventPacket.raw`); with the writer's
        `event_storage` "evt_words" they are stored as sent (`append_packet`), else as
        DSEC-compatible x/y/p/t columns (attr `storage` says which)."""
        self._check_new_device(name)
        if not (0 < width <= 65536 and 0 < height <= 65536):
            raise TakeError(f"{self.path}: event sensor {name!r}: geometry {width}x{height} out of range")
        g = self._f[EVENTS_GROUP].create_group(name)
        _write_info_attrs(g, info, settings_json)
        if evt_format in EVT_FORMATS and self._cfg.event_storage == Storage.EVT_WORDS:
            self._events[name] = EvtWordsSink.create(name, g, width, height, evt_format)
        else:
            g.attrs[Events.STORAGE] = Storage.COLUMNS
            if self._cfg.event_storage == Storage.EVT_WORDS:
                why = "carry no EVT words" if evt_format is None else f"are {evt_format}, not EVT words"
                g.attrs[Events.STORAGE_NOTE] = f"columns: the sensor's packets {why}"
            sink = EventSink.create(name, g, width, height, self._cfg.event_chunk, self._ev_opts)
            self._events[name] = sink
        self._f.flush()

    def add_calibration(
        self,
        device: str,
        intrinsics: dict[str, Any],
        pose: dict[str, Any] | None,
        source: str,
        board: tuple[Any, Any] | None = None,
    ) -> None:
        """Store a calibration known at capture (a simulator's ground truth) as
        `rigd.take.calibration` stores one after it; `board`: the board plane's (R, t) in the rig."""
        self._check_writable()
        if device not in self._cameras and device not in self._events:
            raise TakeError(f"{self.path}: calibration for {device!r}, which is not a device of the take")
        write_calibration_group(self._f, device, intrinsics, pose, source)
        if board is not None:
            write_board_pose(self._f, board[0], board[1], source)
        self._f.flush()

    # -- appends -----------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise TakeError(f"{self.path}: take is closed")

    def _check_writable(self) -> None:
        self._check_open()
        if self._state != "recording":
            raise TakeError(f"{self.path}: take is {self._state}; no more data can be written")

    def _sensor(self, name: str) -> EventSink | EvtWordsSink:
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
        self._pulses.add(batch)

    def append_frame(self, name: str, frame: Frame) -> None:
        """Write one frame image (one HDF5 write) and buffer its timestamps (device clock)."""
        self._check_writable()
        try:
            cam = self._cameras[name]
        except KeyError:
            raise TakeError(f"{self.path}: unknown camera {name!r} (add_camera first)") from None
        cam.add_frame(frame, self.path)

    def append_events(self, name: str, events: EventArray) -> None:
        """Buffer events (device clock); checked whole before any of the batch is kept."""
        sink = self._sensor(name)
        if isinstance(sink, EvtWordsSink):
            raise TakeError(f"{self.path}: event sensor {name!r} stores EVT words: use append_packet")
        sink.add_events(events, self.path)

    def append_packet(self, name: str, packet: EventPacket) -> None:
        """Store a packet: its words as sent where the sensor stores them, else its events
        as columns; its trigger edges either way (events checked whole first)."""
        sink = self._sensor(name)
        if isinstance(sink, EvtWordsSink):
            try:
                sink.add_packet(packet, self.path)
            except WriteDeferredError:
                sink.add_triggers(packet.triggers, packet.host_time_ns)  # the packet is the take's
                raise
        elif packet.n_events:
            sink.add_events(packet.events, self.path)
        sink.add_triggers(packet.triggers, packet.host_time_ns)

    def compress_events(self, on: bool) -> None:
        """Whether EVT-word chunks are compressed from here on (off: stored as they are, while
        the writer catches up; the take stays readable, only larger)."""
        for sink in self._events.values():
            if isinstance(sink, EvtWordsSink):
                sink.compress = on

    def append_triggers(self, name: str, triggers: TriggerEvents, host_time_ns: int | None = None) -> None:
        """Buffer trigger-in edges of an event sensor (device clock).

        `host_time_ns`: host monotonic ns when the packet carrying these edges arrived (all
        edges of one packet share it); recovery matches edges to pulses with it. None: -1.
        """
        self._sensor(name).add_triggers(triggers, host_time_ns)

    # -- buffer writes -----------------------------------------------------------------
    def _write_all(self, *, final: bool = True) -> None:
        """Write every buffer: events up to the last whole chunk and the rest to their tail
        (a flush), or all of it to the main datasets (`final`: close, fail, finalize)."""
        for sink in self._events.values():
            if isinstance(sink, EvtWordsSink):
                sink.write(final=final)
            else:
                sink.write_events(whole_chunks_only=not final)
                if not final:
                    sink.write_tail()
            sink.write_triggers()
        for cam in self._cameras.values():
            cam.write_series()
            cam.trim_images()
        self._pulses.write()

    def _drop_tails(self) -> None:
        for sink in self._events.values():
            sink.drop_tails()

    def _drop_tails_after_flush(self) -> None:
        self._f.flush()  # the tails are redundant only once the main data is on disk
        self._drop_tails()

    def _discard_pending(self) -> None:
        """Let HDF5 close a file it failed to write (rigd.take.refused)."""
        try:
            self._syncer.wait()  # not on a file descriptor about to be swapped
        except OSError as exc:
            log.error("take %s: the last flush's fsync failed too: %s", self.path, exc)
        discard_pending_writes(self._f, self.path)

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
                _write_journal(f, blob, n)
            # Fixed-size values rewritten in place in the root object header (no heap churn).
            f.attrs.modify(Root.FLUSH_COUNT, np.int64(n))
            f.attrs.modify(Root.LAST_FLUSH_UTC, np.bytes_(utc_now("milliseconds")))
            f.flush()
            if self._cfg.fsync:
                self._syncer.start(int(f.id.get_vfd_handle()))
        except RuntimeError as exc:
            raise as_oserror(exc) from exc
        self._flush_count = n
        took = time.perf_counter() - t0
        self.flush_seconds_total += took
        self.flush_seconds_max = max(self.flush_seconds_max, took)

    # -- finalize ----------------------------------------------------------------------
    def _finalizer(self) -> Finalizer:
        return Finalizer(
            self._f,
            self.path,
            self._events,
            self._cameras,
            event_opts=self._ev_opts,
            small_opts=self._small_opts,
        )

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
        label_tree(self._f)  # units and compression filters named for plain HDF5 users
        self._f.flush()
        finalizer = self._finalizer()
        plan = finalizer.plan(maps, frame_pulse_index, report)
        finalizer.start(plan, frame_pulse_index, report)
        self._plan = plan
        self._state = "finalizing"
        self._run_finalize(finalizer, plan)

    def continue_finalize(self, report: SyncReport | None = None) -> None:
        """Finish a finalize that a crash cut short, with the maps and t_offset it started with.

        `report` replaces the stored sync report (recovery adds its notes); the mapping never
        changes, so the result is the same as an uninterrupted finalize.
        """
        self._check_open()
        if self._plan is None or self._state != "finalizing":
            raise TakeError(f"{self.path}: no interrupted finalize to continue (status {self._state})")
        finalizer = self._finalizer()
        if report is not None:
            finalizer.write_sync(self._plan.maps, report)
        self._run_finalize(finalizer, self._plan)

    def _run_finalize(self, finalizer: Finalizer, plan: FinalizePlan) -> None:
        finalizer.run(plan)
        self._state = "complete"
        finalizer.drop_bookkeeping()
        log.info("take %s finalized (t_offset %d us)", self.path, plan.t_offset)

    # -- end of life -------------------------------------------------------------------
    def mark_recovered(self, recovery_report_json: str | None, *, keep_failure_reason: bool = False) -> None:
        """Stamp a take sealed by recovery (`recovered_utc`, and the report once known).

        A take that a crashed finalize had marked failed and that is now complete drops its
        stale `failure_reason`; the recovery report keeps it. `keep_failure_reason`: the
        take's own writer failed it (disk full) before finalize; sealed `complete`, it keeps
        the reason, so readers see both that it is usable and why it is short.
        """
        self._check_open()
        f = self._f
        if Root.RECOVERED_UTC not in f.attrs:
            f.attrs[Root.RECOVERED_UTC] = utc_now()
        if recovery_report_json is not None:
            f.attrs[Root.RECOVERY_REPORT] = recovery_report_json
        if self._state == "complete" and Root.FAILURE_REASON in f.attrs and not keep_failure_reason:
            del f.attrs[Root.FAILURE_REASON]
        f.flush()

    def fail(self, reason: str) -> None:
        """Mark the take failed with a reason; everything written so far stays readable.

        Writes what is buffered, then the status, and flushes; a write that fails (disk full)
        is raised afterwards as OSError, anything else as it was. Where the file refuses the
        buffered writes, or the disk has too little room (rigd.take.refused), nothing more
        is written: the take stays as last flushed (`rigd recover` seals it) and `close`
        writes nothing either.
        """
        self._check_open()
        if self._state == "complete":
            log.warning("take %s: fail(%r) after finalize ignored", self.path, reason)
            return
        error: Exception | None = None
        recording = self._state == "recording"
        try:
            self._syncer.wait()
            if recording:
                self._write_all()
        except Exception as exc:  # noqa: BLE001 - raised below, once the status is set
            error = exc
        self._state = "failed"
        refused = isinstance(error, OSError | RuntimeError)
        if not refused and (no_room := no_room_to_flush(self.path)) is not None:
            error, refused = no_room, True
        if not refused:
            try:
                if recording:
                    self._drop_tails_after_flush()
                self._f.attrs[Root.STATUS] = Status.FAILED
                self._f.attrs[Root.FAILURE_REASON] = reason
                self._f.flush()
            except (OSError, RuntimeError) as exc:
                error = error or exc
                refused = True
        if refused:
            # The file refuses writes even now (no room freed, a size limit), or the disk has no
            # room for the metadata: the take stays as last flushed, no flush tried (refused.py).
            assert error is not None
            self._refused = as_oserror(error)
            log.error(
                "take %s marked failed (%s); the file refuses writes: it stays as last flushed",
                self.path,
                reason,
            )
            raise self._refused from error
        log.error("take %s marked failed: %s", self.path, reason)
        if error is not None:
            raise error

    def close(self) -> None:
        """Write buffers and close. Idempotent; an unfinalized take stays "recording".

        Raises OSError if a write fails (disk full). The file is closed all the same, with what
        HDF5 could not write discarded (see _discard_pending): it stays as last flushed, for
        `rigd recover`, and its lock is released.
        """
        if self._closed:
            return
        error: BaseException | None = self._refused
        try:
            self._syncer.wait()
            if error is not None:
                pass  # `fail` found the file refusing writes: nothing more is tried
            elif self._state == "recording":
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
            raise as_oserror(error) from error

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
        self._f.attrs[Root.END_REASON] = reason

    def set_window(
        self,
        start_us: int | None,
        end_us: int | None,
        margin_us: int,
        outside: Mapping[str, Mapping[str, int]],
    ) -> None:
        """The take's trigger window in rig us (None: unknown, no pulse) and, per device, what
        arrived outside it and was not written."""
        self._check_writable()
        attrs = self._f.attrs
        for key, value in ((Root.WINDOW_START, start_us), (Root.WINDOW_END, end_us)):
            if value is not None:
                attrs[key] = np.int64(value)
        attrs[Root.WINDOW_MARGIN] = np.int64(margin_us)
        attrs[Root.WINDOW_OUTSIDE] = json.dumps({k: dict(v) for k, v in outside.items()}, sort_keys=True)

    def window_outside(self) -> dict[str, dict[str, int]]:
        """Per device, what lies outside the window as the file records it (after finalize, with
        the EVT-word sensors' stored events outside it, `stored_before`/`stored_after`)."""
        text = self._f.attrs.get(Root.WINDOW_OUTSIDE)
        return {} if text is None else dict(json.loads(text))

    def events_in_take(self) -> dict[str, int]:
        """Events each sensor's readers see: for EVT-word sensors, once finalized, those inside
        the take window (a packet across its edge is stored whole and clipped on read)."""
        out = {}
        for name, sink in self._events.items():
            inside = sink.group.attrs.get(Events.EVENTS_IN_WINDOW) if isinstance(sink, EvtWordsSink) else None
            out[name] = sink.n_written if inside is None else int(inside)
        return out

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
        sinks: list[tuple[str, EventSink | EvtWordsSink | CameraSink | PulseSink]] = [
            *self._events.items(),
            *self._cameras.items(),
            ("trigger", self._pulses),
        ]
        for name, sink in sinks:
            st = sink.stats
            if not self._closed:
                st.stored_bytes = int(sum(d.id.get_storage_size() for d in sink.datasets()))
            out[name] = DeviceWriteStats(
                st.kind, st.items, st.raw_bytes, st.stored_bytes, st.uncompressed_chunks
            )
        return out


def _resume_repairs(f: h5py.File, path: Path, plan: FinalizePlan | None) -> list[Trim]:
    """Trim what the kill left half-written; a take whose finalize had started is only
    checked (its `t` is part rig, part device time now, so only lengths can be)."""
    if plan is None:
        repairs = check_repair(f, path, apply=True)
        if TRUNCATED_EOF_ATTR in f.attrs:  # nothing past the old end is referenced any more
            del f.attrs[TRUNCATED_EOF_ATTR]
        return repairs
    found = check_repair(f, path, apply=False, check_order=False)
    if found:
        what = "; ".join(f"{t.hpath}: {t.reason}" for t in found)
        raise TakeFormatError(
            f"{path}: finalize had started, yet the data is inconsistent ({what}); refusing to touch it"
        )
    return []


def _write_info_attrs(obj: h5py.HLObject, info: DeviceInfo, settings_json: str | None) -> None:
    for key, value in info.model_dump().items():
        if isinstance(value, str):  # scalar identity fields as plain attributes
            obj.attrs[key] = value
    obj.attrs[Device.INFO_JSON] = info.model_dump_json()
    if settings_json is not None:
        obj.attrs[Device.SETTINGS_JSON] = settings_json


def _write_journal(f: h5py.File, blob: bytes, n: int) -> None:
    """Overwrite the older of the two slots in place; the newer survives a torn write."""
    node = f.get(Root.JOURNAL)
    if node is None or node.shape[1] < len(blob):
        cap = max(_JOURNAL_MIN_BYTES, 1 << (2 * len(blob) - 1).bit_length())
        old = np.zeros((2, 0), np.uint8) if node is None else node[...]
        if node is not None:
            del f[Root.JOURNAL]
        # Contiguous and unfiltered: every later write lands on the same bytes.
        node = f.create_dataset(Root.JOURNAL, shape=(2, cap), dtype=np.uint8, fillvalue=0)
        node[:, : old.shape[1]] = old
    row = np.zeros(node.shape[1], np.uint8)
    row[: len(blob)] = np.frombuffer(blob, np.uint8)
    node[n % 2] = row
