"""TakeWriter: streams one take into an HDF5 file.

Used by exactly one writer thread. While recording every timestamp is stored in its
device clock (the clock maps are only known once all pulses are in); `finalize` rewrites
the times in place, chunk by chunk, so memory stays constant however long the take is.
The layout is documented in docs/take-format.md; names come from `rigd.core.schema`.

Crash safety: `flush()` leaves the file consistent up to that point (plus a JSON journal of
the caller's loss bookkeeping).

The writer records, and only records. It owns the take's open state
(`rigd.take.take_state.TakeState`: the file, one store per device) and hands it to the steps
that end or reopen a take: `rigd.take.seal` finalizes it (the rig-time rewrite of
`rigd.take.finalize`), fails it or stamps it recovered; `rigd.take.resume` reopens a take whose
writer died, trims what the kill left half-written and continues a finalize cut short. Event
sensors are stored through one interface (`rigd.take.event_store`), columns or EVT words alike.
The names other packages import from here are re-exported from the modules they live in.
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
from numpy.typing import DTypeLike

from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.errors import TakeError
from rigd.core.events import EventArray, EventPacket, TriggerEvents
from rigd.core.frames import Frame
from rigd.core.layout import (
    EVENTS_GROUP,
    FRAMES_GROUP,
    SYNC_GROUP,
    TRIGGER_GROUP,
    Device,
    Pulses,
    Root,
    Status,
    TimeDomain,
)
from rigd.core.schema import SCHEMA_NAME, SCHEMA_VERSION, encode_journal
from rigd.core.settings import WriterConfig
from rigd.take.calibration import write_board_pose, write_calibration_group
from rigd.take.event_store import EventStore, NewSensor, event_store
from rigd.take.h5file import (
    TRUNCATED_EOF_ATTR,
    ZeroPadded,
    as_oserror,
    check_header,
    compression_options,
    fsync_dir,
    is_lock_error,
    open_h5,
    require_dataset,
    require_group,
    utc_now,
)
from rigd.take.repair import Trim, check_repair, stored_prefix
from rigd.take.sinks import CameraSink, DeviceWriteStats, PulseSink
from rigd.take.tails import tail_rows
from rigd.take.take_state import WRITE_CHUNK_CACHE_BYTES, TakeState

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


class TakeWriter:
    """Records one take file; see docs/take-format.md for the layout it produces.

    Ending the take (finalize, fail, the recovery stamp) is `rigd.take.seal`'s, reopening one
    whose writer died `rigd.take.resume`'s; both work on `state`.
    """

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
        pulses = PulseSink.create(trig.create_group(Pulses.GROUP))
        self._s = TakeState(path, f, config, pulses, status="recording")
        f.flush()
        log.info("take %s created (%s)", path, take_id)

    @classmethod
    def over(cls, state: TakeState) -> TakeWriter:
        """A writer over an already open take (`rigd.take.resume`)."""
        w = cls.__new__(cls)
        w._s = state
        return w

    @property
    def state(self) -> TakeState:
        """The open take, for the steps that end or reopen it (`rigd.take.seal`, `resume`)."""
        return self._s

    @property
    def path(self) -> Path:
        return self._s.path

    # -- setup -------------------------------------------------------------------------
    def _check_new_device(self, name: str) -> None:
        s = self._s
        s.check_writable()
        if not _NAME_RE.match(name):
            raise TakeError(f"{s.path}: device name {name!r} is not a valid take name ({_NAME_RE.pattern})")
        if name in s.stores or name in s.cameras:
            raise TakeError(f"{s.path}: device {name!r} added twice")

    def add_trigger(self, info: DeviceInfo) -> None:
        """Record the trigger box identity on `/trigger`."""
        s = self._s
        s.check_writable()
        _write_info_attrs(s.f[TRIGGER_GROUP], info, None)
        s.has_trigger = True
        s.f.flush()  # the layout is on disk before any data: a crash keeps the devices

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
        s = self._s
        self._check_new_device(name)
        shape = tuple(int(n) for n in shape)
        if len(shape) not in (2, 3) or min(shape) <= 0:
            raise TakeError(f"{s.path}: camera {name!r}: frame shape {shape} is not (H, W) or (H, W, C)")
        fmt = CameraSink.check_format(pixel_format, shape, np.dtype(dtype), f"{s.path}: camera {name!r}")
        g = s.f[FRAMES_GROUP].create_group(name)
        _write_info_attrs(g, info, settings_json)
        s.cameras[name] = CameraSink.create(name, g, shape, np.dtype(dtype), s.frame_opts, fmt)
        s.f.flush()

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
        DSEC-compatible x/y/p/t columns (attr `storage` says which; `rigd.take.event_store`)."""
        s = self._s
        self._check_new_device(name)
        if not (0 < width <= 65536 and 0 < height <= 65536):
            raise TakeError(f"{s.path}: event sensor {name!r}: geometry {width}x{height} out of range")
        g = s.f[EVENTS_GROUP].create_group(name)
        _write_info_attrs(g, info, settings_json)
        new = NewSensor(width, height, evt_format)
        s.stores[name] = event_store(name, g, str(s.path), s.config, new=new, column_opts=s.event_opts)
        s.f.flush()

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
        s = self._s
        s.check_writable()
        if device not in s.cameras and device not in s.stores:
            raise TakeError(f"{s.path}: calibration for {device!r}, which is not a device of the take")
        write_calibration_group(s.f, device, intrinsics, pose, source)
        if board is not None:
            write_board_pose(s.f, board[0], board[1], source)
        s.f.flush()

    # -- appends -----------------------------------------------------------------------
    def _sensor(self, name: str) -> EventStore:
        s = self._s
        s.check_writable()
        try:
            store = s.stores[name]
        except KeyError:
            raise TakeError(f"{s.path}: unknown event sensor {name!r} (add_event_sensor first)") from None
        if not store.appendable:
            raise TakeError(f"{s.path}: a resumed take can be finalized or failed, not appended to")
        return store

    def append_pulses(self, batch: PulseBatch) -> None:
        """Buffer trigger box pulses (already rig time)."""
        self._s.check_writable()
        self._s.pulses.add(batch)

    def append_frame(self, name: str, frame: Frame) -> None:
        """Write one frame image (one HDF5 write) and buffer its timestamps (device clock)."""
        s = self._s
        s.check_writable()
        try:
            cam = s.cameras[name]
        except KeyError:
            raise TakeError(f"{s.path}: unknown camera {name!r} (add_camera first)") from None
        cam.add_frame(frame, s.path)

    def append_events(self, name: str, events: EventArray) -> None:
        """Buffer events (device clock); checked whole before any of the batch is kept. A
        sensor stored as EVT words refuses them (it takes packets)."""
        self._sensor(name).add_events(events, self._s.path)

    def append_packet(self, name: str, packet: EventPacket) -> None:
        """Store a packet: its words as sent where the sensor stores them, else its events
        as columns; its trigger edges either way (events checked whole first)."""
        self._sensor(name).append_packet(packet, self._s.path)

    def compress_events(self, on: bool) -> None:
        """Whether EVT-word chunks are compressed from here on (off: stored as they are, while
        the writer catches up; the take stays readable, only larger)."""
        for store in self._s.stores.values():
            store.set_compress(on)

    def append_triggers(self, name: str, triggers: TriggerEvents, host_time_ns: int | None = None) -> None:
        """Buffer trigger-in edges of an event sensor (device clock).

        `host_time_ns`: host monotonic ns when the packet carrying these edges arrived (all
        edges of one packet share it); recovery matches edges to pulses with it. None: -1.
        """
        self._sensor(name).add_triggers(triggers, host_time_ns)

    def flush(self, journal: Mapping[str, Any] | None = None) -> None:
        """Write every buffer and flush HDF5, so a crash from here on loses nothing written.

        `journal` (JSON-serialisable: the caller's losses, device counters, failed devices,
        trigger link counters, warnings) replaces `/journal_json`, so a crash does not lose the
        loss bookkeeping; recovery merges it into the sync report. Also bumps the root attrs
        `flush_count` and `last_flush_utc`. Cheap: buffered data is written once; partial
        event chunks are rewritten later.
        """
        s = self._s
        s.check_open()
        t0 = time.perf_counter()
        n = s.flush_count + 1
        blob = None
        if journal is not None:
            try:
                blob = encode_journal(n, journal)
            except (TypeError, ValueError) as exc:
                raise TakeError(f"{s.path}: flush journal is not JSON-serialisable: {exc}") from exc
        try:
            if s.status == "recording":
                s.write_all(final=False)
            f = s.f
            if blob is not None:
                _write_journal(f, blob, n)
            # Fixed-size values rewritten in place in the root object header (no heap churn).
            f.attrs.modify(Root.FLUSH_COUNT, np.int64(n))
            f.attrs.modify(Root.LAST_FLUSH_UTC, np.bytes_(utc_now("milliseconds")))
            f.flush()
            if s.config.fsync:
                s.syncer.start(int(f.id.get_vfd_handle()))
        except RuntimeError as exc:
            raise as_oserror(exc) from exc
        s.flush_count = n
        took = time.perf_counter() - t0
        s.flush_seconds_total += took
        s.flush_seconds_max = max(s.flush_seconds_max, took)

    def close(self) -> None:
        """Write buffers and close. Idempotent; an unfinalized take stays "recording".

        Raises OSError if a write fails (disk full). The file is closed all the same, with what
        HDF5 could not write discarded (`TakeState.discard_pending`): it stays as last flushed,
        for `rigd recover`, and its lock is released.
        """
        s = self._s
        if s.closed:
            return
        error: BaseException | None = s.refused
        try:
            s.syncer.wait()
            if error is not None:
                pass  # a fail found the file refusing writes: nothing more is tried
            elif s.status == "recording":
                s.write_all()
                s.drop_tails_after_flush()
            else:
                s.f.flush()
        except (OSError, RuntimeError) as exc:
            error = exc
        s.closed = True
        try:
            if error is not None:
                s.discard_pending()
            elif s.config.fsync:
                s.f.flush()
                os.fsync(s.f.id.get_vfd_handle())
            s.f.close()
            if error is None and s.config.fsync:
                fsync_dir(s.path.parent)  # the file's directory entry, for a new take
        except (OSError, RuntimeError) as exc:
            error = error or exc
            _UNCLOSABLE.append(self)
            log.error("take %s could not be closed (%s); its handle is kept until exit", s.path, exc)
        log.info("take %s closed (%s)", s.path, s.status)
        if error is not None:
            raise as_oserror(error) from error

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def window_outside(self) -> dict[str, dict[str, int]]:
        """Per device, what lies outside the window as the file records it (after finalize, with
        the EVT-word sensors' stored events outside it, `stored_before`/`stored_after`)."""
        text = self._s.f.attrs.get(Root.WINDOW_OUTSIDE)
        return {} if text is None else dict(json.loads(text))

    def events_in_take(self) -> dict[str, int]:
        """Events each sensor's readers see: for EVT-word sensors, once finalized, those inside
        the take window (a packet across its edge is stored whole and clipped on read)."""
        return {name: store.events_in_take() for name, store in self._s.stores.items()}

    @property
    def flush_count(self) -> int:
        return self._s.flush_count

    @property
    def flush_seconds_max(self) -> float:
        """The longest flush (with `fsync`, the wait for the disk too)."""
        return self._s.flush_seconds_max

    @property
    def status(self) -> str:
        return self._s.status

    @property
    def stats(self) -> dict[str, DeviceWriteStats]:
        """Per device (and "trigger"): items and bytes taken in, bytes stored in the file."""
        s = self._s
        out: dict[str, DeviceWriteStats] = {}
        sinks: list[tuple[str, EventStore | CameraSink | PulseSink]] = [
            *s.stores.items(),
            *s.cameras.items(),
            ("trigger", s.pulses),
        ]
        for name, sink in sinks:
            st = sink.stats
            if not s.closed:
                st.stored_bytes = int(sum(d.id.get_storage_size() for d in sink.datasets()))
            out[name] = DeviceWriteStats(
                st.kind, st.items, st.raw_bytes, st.stored_bytes, st.uncompressed_chunks
            )
        return out


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
