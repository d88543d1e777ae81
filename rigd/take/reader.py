"""Read-only access to take files for training jobs.

Nothing here loads a whole event dataset unless asked for all of it: a time window is
narrowed with the DSEC `ms_to_idx` index to the events of the milliseconds it touches, whose
`t` is read once and searched for both edges; `x, y, p` are then read for exactly the window.
Dataset handles stay open for the Take's life, so a read costs no lookups and HDF5 decodes
only the chunks the window overlaps (random training windows: docs/take-format.md).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Self

import h5py
import hdf5plugin  # noqa: F401  (registers the LZ4 / Zstd filters with h5py)
import numpy as np
from numpy.typing import NDArray
from pydantic import ValidationError

from rigd.core.devices import PulseBatch
from rigd.core.errors import TakeError, TakeFormatError
from rigd.core.events import EventArray, TriggerEvents
from rigd.core.layout import (
    EVENT_DTYPES,
    EVENTS_GROUP,
    FRAME_SERIES,
    FRAMES_GROUP,
    PULSE_SERIES,
    PULSES_PATH,
    SYNC_GROUP,
    SYNC_REPORT_PATH,
    TRIGGER_DTYPES,
    TRIGGER_GROUP,
    Device,
    Events,
    Pulses,
    Root,
    Status,
    TimeDomain,
    TriggerEdges,
)
from rigd.core.schema import SCHEMA_NAME, SCHEMA_VERSION, SyncReport, decode_journal, has_item
from rigd.core.timebase import ClockMap
from rigd.take.calibration import read_board_pose, read_calibration
from rigd.take.evt_read import EvtWordsEvents
from rigd.take.evt_sink import is_evt_words
from rigd.take.frame_series import FrameSeries
from rigd.take.h5file import attr_text, describe_open_error
from rigd.take.summary import CameraSummary, EventSensorSummary, TakeSummary
from rigd.take.tails import tail_rows
from rigd.take.verdict import take_verdict

log = logging.getLogger(__name__)

#: Events read per step by iter_events (bounded memory, few HDF5 calls).
_READ_BLOCK = 1 << 20
#: Raw-data chunk cache per open dataset (held for the Take's life, so per column and sensor):
#: keeps the chunk a sequential read shares with the next block decoded; random windows rarely
#: share one, and 16 MiB read them no faster (bench.random_windows' takes).
_CHUNK_CACHE_BYTES = 4 << 20
#: A time window whose ms bracket holds at most this many events reads its `t` in one call.
_WINDOW_T_MAX = 1 << 22


@dataclass(slots=True)
class _EventColumns:
    """Open handles of one sensor's event datasets: opening a dataset per read costs a name
    lookup and starts it with an empty chunk cache."""

    x: h5py.Dataset
    y: h5py.Dataset
    p: h5py.Dataset
    t: h5py.Dataset
    ms_to_idx: h5py.Dataset | None

    @property
    def n(self) -> int:
        return int(self.t.shape[0])


def _ms_bracket(ms_to_idx: h5py.Dataset, rel: int, n: int) -> tuple[int, int]:
    """[lo, hi): the events that may hold the first `t >= rel` (t relative to t_offset), from
    the ms index entries floor(rel/1000) and ceil(rel/1000), read in one call."""
    n_ms = int(ms_to_idx.shape[0])
    a, b = rel // 1000, max(-(-rel // 1000), 0)
    s, e = max(a, 0), min(b, n_ms - 1)
    vals = np.asarray(ms_to_idx[s : e + 1], dtype=np.int64) if s <= e else np.zeros(0, np.int64)
    lo = 0 if a < 0 else (n if a >= n_ms else int(vals[0]))
    hi = n if b >= n_ms else int(vals[b - s])
    return lo, max(lo, hi)


def _attr_str(obj: h5py.HLObject, key: str, default: str = "") -> str:
    return attr_text(obj.attrs.get(key, default))


def _finite(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)


class Take:
    """An open take file (read-only). Use as a context manager or call close()."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self._f = h5py.File(self.path, "r", rdcc_nbytes=_CHUNK_CACHE_BYTES, rdcc_nslots=10007)
        except (OSError, ValueError) as exc:
            raise TakeFormatError(describe_open_error(self.path, exc)) from exc
        try:
            self._check_header()
            self._check_layout()
        except BaseException:
            self._f.close()
            raise
        self._t_offset: dict[str, int] = {}
        self._columns: dict[str, _EventColumns] = {}
        self._evt: dict[str, EvtWordsEvents | None] = {}

    def _check_header(self) -> None:
        f = self._f
        schema = _attr_str(f, Root.SCHEMA)
        if schema != SCHEMA_NAME:
            raise TakeFormatError(f"{self.path}: /: attr schema is {schema!r}, expected {SCHEMA_NAME!r}")
        major = _attr_str(f, Root.SCHEMA_VERSION).split(".")[0]
        if major != SCHEMA_VERSION.split(".")[0]:
            raise TakeFormatError(
                f"{self.path}: /: schema_version {self.schema_version!r} is not readable by this rigd "
                f"(reads {SCHEMA_VERSION.split('.')[0]}.x)"
            )

    def _required(self) -> Iterator[str]:
        """HDF5 paths every reader method relies on, for the take's version and time domain."""
        f = self._f
        version = _attr_str(f, Root.SCHEMA_VERSION, SCHEMA_VERSION)
        rig = _attr_str(f, Root.TIME_DOMAIN) == TimeDomain.RIG
        for name in self.event_sensors:
            base = f"{EVENTS_GROUP}/{name}"
            g = f.get(base)
            if isinstance(g, h5py.Group) and is_evt_words(g):
                yield from (f"{base}/evt_words", f"{base}/evt_index")
            else:
                yield from (f"{base}/{k}" for k in EVENT_DTYPES)
            yield f"{base}/{Events.T_OFFSET}"
            if rig and not (isinstance(g, h5py.Group) and is_evt_words(g)):
                yield f"{base}/{Events.MS_TO_IDX}"
            trig = (k for k in TRIGGER_DTYPES if has_item(version, f"{Events.TRIGGER}/{k}"))
            yield from (f"{base}/trigger/{k}" for k in trig)
        for name in self.cameras:
            yield f"{FRAMES_GROUP}/{name}/images"
            yield from (f"{FRAMES_GROUP}/{name}/{k}" for k in FRAME_SERIES)
        yield from (f"{TRIGGER_GROUP}/pulses/{k}" for k in PULSE_SERIES)

    def _check_layout(self) -> None:
        """Refuse a damaged take on open with the first missing dataset named, instead of a
        KeyError from whichever read reaches it first."""
        for name in (EVENTS_GROUP, FRAMES_GROUP):
            node = self._f.get(name)
            if node is not None and not isinstance(node, h5py.Group):
                raise TakeFormatError(f"{self.path}: /{name} is not a group")
        for hpath in self._required():
            if not isinstance(self._f.get(hpath), h5py.Dataset):
                raise TakeFormatError(f"{self.path}: /{hpath}: required dataset is missing (damaged take)")

    # -- lifecycle ---------------------------------------------------------------------
    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- metadata ----------------------------------------------------------------------
    @property
    def status(self) -> str:
        return _attr_str(self._f, Root.STATUS)

    @property
    def schema_version(self) -> str:
        return _attr_str(self._f, Root.SCHEMA_VERSION)

    @property
    def take_id(self) -> str:
        return _attr_str(self._f, Root.TAKE_ID)

    @property
    def time_domain(self) -> str:
        return _attr_str(self._f, Root.TIME_DOMAIN)

    @property
    def config(self) -> dict[str, Any]:
        raw = self._dataset(Root.CONFIG)[()]
        text = attr_text(raw)
        return self._json_object(text, f"/{Root.CONFIG}")

    @property
    def journal(self) -> dict[str, Any] | None:
        """The loss bookkeeping of the last flush (`/journal_json`, newest readable slot), or None."""
        node = self._f.get(Root.JOURNAL)
        if not isinstance(node, h5py.Dataset):
            return None
        found = decode_journal(np.asarray(node[...]))
        return None if found is None else found[1]

    @property
    def end_reason(self) -> str | None:
        """Why the recording ended (set by the capture; None for older or converted takes)."""
        return _attr_str(self._f, Root.END_REASON) if Root.END_REASON in self._f.attrs else None

    @property
    def recovered_utc(self) -> str | None:
        """When `rigd recover` sealed this take after a crash; None for a take closed normally."""
        return _attr_str(self._f, Root.RECOVERED_UTC) if Root.RECOVERED_UTC in self._f.attrs else None

    @property
    def recovery_report(self) -> dict[str, Any] | None:
        """The RecoveryReport (as a dict) of a recovered take: what was trimmed and why."""
        if Root.RECOVERY_REPORT not in self._f.attrs:
            return None
        return self._json_object(_attr_str(self._f, Root.RECOVERY_REPORT), f"/ attr {Root.RECOVERY_REPORT}")

    def _json_object(self, text: str, where: str) -> dict[str, Any]:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise TakeFormatError(f"{self.path}: {where} is not valid JSON: {exc}") from exc
        if not isinstance(data, dict):
            raise TakeFormatError(f"{self.path}: {where} is not a JSON object")
        return data

    @property
    def calibration(self) -> dict[str, dict[str, Any]] | None:
        """Calibrations stored in the take by `rigd calibrate ... --into-take`, by device."""
        return read_calibration(self._f)

    @property
    def board_pose(self) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
        """(R, t) of the board plane in the rig frame (x_rig = R x_board + t), when stored."""
        return read_board_pose(self._f)

    @property
    def sync_report(self) -> SyncReport | None:
        """The sync report, or None for a take that was never finalized."""
        node = self._f.get(SYNC_REPORT_PATH)
        if node is None:
            return None
        raw = node[()]
        text = attr_text(raw)
        try:
            return SyncReport.model_validate_json(text)
        except ValidationError as exc:
            raise TakeFormatError(f"{self.path}: /{SYNC_GROUP}/report_json does not parse: {exc}") from exc

    @property
    def cameras(self) -> list[str]:
        return sorted(self._f.get(FRAMES_GROUP, {}).keys())

    @property
    def event_sensors(self) -> list[str]:
        return sorted(self._f.get(EVENTS_GROUP, {}).keys())

    def _dataset(self, hpath: str) -> h5py.Dataset:
        node = self._f.get(hpath)
        if not isinstance(node, h5py.Dataset):
            raise TakeFormatError(f"{self.path}: /{hpath} is missing or not a dataset")
        return node

    def _sensor_group(self, sensor: str) -> h5py.Group:
        g = self._f.get(f"{EVENTS_GROUP}/{sensor}")
        if not isinstance(g, h5py.Group):
            raise TakeError(f"{self.path}: no event sensor {sensor!r} (has {self.event_sensors})")
        return g

    def _require_rig(self, hpath: str) -> None:
        if self.time_domain != TimeDomain.RIG:
            raise TakeError(
                f"{self.path}: {hpath}: time queries need rig time, but this take was never finalized "
                f"(status {self.status!r}, times are still in each device's own clock)"
            )

    def _offset(self, sensor: str) -> int:
        if sensor not in self._t_offset:
            g = self._sensor_group(sensor)
            self._t_offset[sensor] = int(g[Events.T_OFFSET][()]) if Events.T_OFFSET in g else 0
        return self._t_offset[sensor]

    # -- events ------------------------------------------------------------------------
    def _words(self, sensor: str, *, rig: bool = False) -> EvtWordsEvents | None:
        """The sensor's stored EVT words (None: it stores x/y/p/t columns); `rig`: refuse a
        take never finalized (its times are still in the device clock)."""
        if sensor not in self._evt:
            g = self._sensor_group(sensor)
            words = None
            if is_evt_words(g):
                cmap_text = g.attrs.get(Events.CLOCK_MAP) if self.time_domain == TimeDomain.RIG else None
                cmap = None if cmap_text is None else ClockMap(*json.loads(attr_text(cmap_text)))
                lo, hi = json.loads(attr_text(g.attrs.get(Events.WINDOW, "[null, null]")))
                words = EvtWordsEvents(
                    g, self.path, cmap, (lo, hi), with_tail=self.status == Status.RECORDING
                )
            self._evt[sensor] = words
        words = self._evt[sensor]
        if words is not None and rig and words.cmap is None:
            self._require_rig(f"/{EVENTS_GROUP}/{sensor}")
        return words

    def _tail(self, g: h5py.Group) -> tuple[int, int, int]:
        """(main rows, tail slot, tail rows) of a sensor. A take whose writer died before
        `rigd recover` keeps the flushed events past its last whole chunk in `tail_*`
        (see docs/take-format.md); index reads include them."""
        n = int(g[Events.T].shape[0])
        if self.status != Status.RECORDING or Events.TAIL_META not in g.attrs:
            return n, 0, 0
        slot, m = tail_rows(g, n)
        return n, slot, m

    def _n_events(self, g: h5py.Group) -> int:
        if is_evt_words(g):
            return len(self._words(g.name.rsplit("/", 1)[-1]) or ())
        n, _, m = self._tail(g)
        return n + m

    def _cols(self, g: h5py.Group) -> _EventColumns:
        cols = self._columns.get(g.name)
        if cols is None:
            ms = g.get(Events.MS_TO_IDX)
            cols = _EventColumns(
                g[Events.X],
                g[Events.Y],
                g[Events.P],
                g[Events.T],
                ms if isinstance(ms, h5py.Dataset) else None,
            )
            self._columns[g.name] = cols
        return cols

    def _read_events(self, g: h5py.Group, lo: int, hi: int, t_offset: int) -> EventArray:
        n, slot, m = self._tail(g)
        main = self._read_main(g, lo, min(hi, n), t_offset)
        if hi <= n or m == 0:
            return main
        a, b = max(lo, n) - n, min(hi, n + m) - n
        cols = {k: np.asarray(g[f"{Events.TAIL_PREFIX}{k}"][slot, a:b]) for k in EVENT_DTYPES}
        tail = EventArray(
            cols[Events.X].astype(np.uint16),
            cols[Events.Y].astype(np.uint16),
            cols[Events.P].astype(np.int8) * np.int8(2) - np.int8(1),
            cols[Events.T].astype(np.int64) + np.int64(t_offset),
        )
        return EventArray.concatenate([main, tail])

    def _read_main(
        self, g: h5py.Group, lo: int, hi: int, t_offset: int, t_rel: NDArray[np.int64] | None = None
    ) -> EventArray:
        """Events [lo, hi) of the main datasets; `t_rel`: their `t`, when already read."""
        c = self._cols(g)
        hi = max(lo, hi)
        t = np.asarray(c.t[lo:hi] if t_rel is None else t_rel, dtype=np.int64) + np.int64(t_offset)
        p = np.asarray(c.p[lo:hi]).astype(np.int8) * np.int8(2) - np.int8(1)
        x = np.asarray(c.x[lo:hi], dtype=np.uint16)
        return EventArray(x, np.asarray(c.y[lo:hi], dtype=np.uint16), p, t)

    def _first_index(self, g: h5py.Group, ms_to_idx: h5py.Dataset, rel: int, n: int) -> int:
        """First event index with t (relative to t_offset) >= rel: ms_to_idx bracket, then search."""
        lo, hi = _ms_bracket(ms_to_idx, rel, n)
        if lo >= hi:
            return lo
        return lo + int(np.searchsorted(self._cols(g).t[lo:hi], rel, side="left"))

    def _window(self, sensor: str, t_start_us: int, t_end_us: int) -> EventArray:
        """Events with t_start_us <= t < t_end_us: `t` of the window's ms bracket is read once
        and searched for both edges, `x, y, p` only for the window itself."""
        words = self._words(sensor, rig=True)
        if words is not None:
            return words.window(int(t_start_us), int(t_end_us))
        g = self._sensor_group(sensor)
        self._require_rig(f"/{EVENTS_GROUP}/{sensor}")
        c = self._cols(g)
        if c.ms_to_idx is None:
            raise TakeFormatError(f"{self.path}: /{EVENTS_GROUP}/{sensor}/{Events.MS_TO_IDX} is missing")
        off, n = self._offset(sensor), c.n
        rel0, rel1 = int(t_start_us) - off, max(int(t_end_us), int(t_start_us)) - off
        lo, _ = _ms_bracket(c.ms_to_idx, rel0, n)
        _, hi = _ms_bracket(c.ms_to_idx, rel1, n)
        if hi - lo > _WINDOW_T_MAX:  # a long span: search each edge's bracket on its own
            i, j = self._first_index(g, c.ms_to_idx, rel0, n), self._first_index(g, c.ms_to_idx, rel1, n)
            return self._read_main(g, i, max(i, j), off)
        t = np.asarray(c.t[lo:hi], dtype=np.int64)
        i = int(np.searchsorted(t, rel0, side="left"))
        j = max(i, int(np.searchsorted(t, rel1, side="left")))
        return self._read_main(g, lo + i, lo + j, off, t[i:j])

    def event_count(self, sensor: str) -> int:
        return self._n_events(self._sensor_group(sensor))

    def geometry(self, sensor: str) -> tuple[int, int]:
        """(width, height) of an event sensor."""
        g = self._sensor_group(sensor)
        return int(g.attrs[Device.WIDTH]), int(g.attrs[Device.HEIGHT])

    def events_by_index(self, sensor: str, start: int, stop: int) -> EventArray:
        """Events [start, stop) by position; works in either time domain."""
        words = self._words(sensor)
        if words is not None:
            return words.by_index(start, stop)
        g = self._sensor_group(sensor)
        n = self._n_events(g)
        lo, hi = max(0, min(start, n)), max(0, min(stop, n))
        return self._read_events(g, lo, max(lo, hi), self._offset(sensor))

    def events(self, sensor: str, t_start_us: int | None = None, t_end_us: int | None = None) -> EventArray:
        """Events with t_start_us <= t < t_end_us (rig us); no bounds returns all of them.

        Without bounds this also works on a never-finalized take (times then in device clock).
        """
        g = self._sensor_group(sensor)
        words = self._words(sensor)
        if words is not None and (t_start_us is None or t_end_us is None):
            if t_start_us is None and t_end_us is None:
                return words.by_index(0, len(words))
            lo, hi = self._index_range(sensor, t_start_us, t_end_us)
            return words.by_index(lo, hi)
        if t_start_us is None and t_end_us is None:
            return self._read_events(g, 0, self._n_events(g), self._offset(sensor))
        if t_start_us is not None and t_end_us is not None:
            return self._window(sensor, t_start_us, t_end_us)
        lo, hi = self._index_range(sensor, t_start_us, t_end_us)
        return self._read_events(g, lo, hi, self._offset(sensor))

    def event_index(self, sensor: str, t_us: int) -> int:
        """Index of the first event at or after rig time `t_us` (the event count if none), for
        reading on from there in blocks with `events_by_index`."""
        return self._index_range(sensor, int(t_us), None)[0]

    def _index_range(self, sensor: str, t_start_us: int | None, t_end_us: int | None) -> tuple[int, int]:
        words = self._words(sensor, rig=True)
        if words is not None:
            lo = 0 if t_start_us is None else words.index_at(int(t_start_us))
            return lo, max(lo, len(words) if t_end_us is None else words.index_at(int(t_end_us)))
        g = self._sensor_group(sensor)
        self._require_rig(f"/{EVENTS_GROUP}/{sensor}")
        c = self._cols(g)
        ms = c.ms_to_idx
        if ms is None:
            raise TakeFormatError(f"{self.path}: /{EVENTS_GROUP}/{sensor}/{Events.MS_TO_IDX} is missing")
        n = c.n
        off = self._offset(sensor)
        lo = 0 if t_start_us is None else self._first_index(g, ms, int(t_start_us) - off, n)
        hi = n if t_end_us is None else self._first_index(g, ms, int(t_end_us) - off, n)
        return lo, max(lo, hi)

    def event_histogram(self, sensor: str, bin_us: int = 10_000) -> tuple[int, NDArray[np.int64]]:
        """Events per bin of `bin_us` (a multiple of 1 ms), from the ms index alone: a training
        job weighs windows by activity without reading the events. Returns the rig time of bin
        0's start and the counts; bins are aligned to `t_offset` and cover first to last event.
        """
        if bin_us <= 0 or bin_us % 1000:
            raise TakeError(f"{self.path}: bin_us must be a positive multiple of 1000, got {bin_us}")
        words = self._words(sensor, rig=True)
        if words is not None:
            return words.histogram(self._offset(sensor), bin_us)
        g = self._sensor_group(sensor)
        self._require_rig(f"/{EVENTS_GROUP}/{sensor}")
        c = self._cols(g)
        if c.ms_to_idx is None:
            raise TakeFormatError(f"{self.path}: /{EVENTS_GROUP}/{sensor}/{Events.MS_TO_IDX} is missing")
        n, off = c.n, self._offset(sensor)
        if n == 0:
            return off, np.zeros(0, np.int64)
        k0, k1 = int(c.t[0]) // bin_us, int(c.t[n - 1]) // bin_us + 1
        edges = np.arange(k0, k1 + 1, dtype=np.int64) * bin_us  # relative to t_offset
        idx = np.full(edges.size, n, np.int64)
        n_ms, step = int(c.ms_to_idx.shape[0]), bin_us // 1000
        ms = edges // 1000
        on = (edges >= 0) & (ms < n_ms)
        if on.any():
            a, b = int(ms[on][0]), int(ms[on][-1])
            idx[on] = np.asarray(c.ms_to_idx[a : b + 1 : step], dtype=np.int64)
        neg = edges < 0  # before t_offset (the events before the first pulse): search their t
        if neg.any():
            before = int(c.ms_to_idx[0]) if n_ms else n
            idx[neg] = np.searchsorted(np.asarray(c.t[:before], dtype=np.int64), edges[neg], side="left")
        return off + k0 * bin_us, np.diff(idx)

    def iter_events(
        self, sensor: str, window_us: int, t_start_us: int | None = None, t_end_us: int | None = None
    ) -> Iterator[EventArray]:
        """Consecutive windows [t0 + k*w, t0 + (k+1)*w) (possibly empty) up to the last event.

        t0 defaults to the first event. Reads sequentially in large blocks, so iterating a
        whole take costs about one pass over the file.
        """
        if window_us <= 0:
            raise TakeError(f"{self.path}: window_us must be positive, got {window_us}")
        g = self._sensor_group(sensor)
        self._require_rig(f"/{EVENTS_GROUP}/{sensor}")
        span = self.event_span(sensor)
        off = self._offset(sensor)
        if span is None:
            return
        start = span[0] if t_start_us is None else int(t_start_us)
        end = span[1] + 1 if t_end_us is None else int(t_end_us)
        pos, stop = self._index_range(sensor, start, end)
        buf = EventArray.empty()
        w0 = start
        while w0 < end:
            w1 = min(w0 + int(window_us), end)
            while pos < stop and (len(buf) == 0 or int(buf.t[-1]) < w1):
                nxt = min(pos + _READ_BLOCK, stop)
                buf = EventArray.concatenate([buf, self._block(sensor, g, pos, nxt, off)])
                pos = nxt
            k = int(np.searchsorted(buf.t, w1, side="left"))
            yield buf[:k]
            buf = buf[k:]
            w0 = w1

    def _block(self, sensor: str, g: h5py.Group, lo: int, hi: int, off: int) -> EventArray:
        words = self._words(sensor)
        return self._read_events(g, lo, hi, off) if words is None else words.by_index(lo, hi)

    def triggers(self, sensor: str) -> TriggerEvents:
        """Trigger-in edges of a sensor (rig time once finalized; device time in `t_device`)."""
        g = self._sensor_group(sensor)
        tg = g.get(Events.TRIGGER)
        if not isinstance(tg, h5py.Group):
            raise TakeFormatError(f"{self.path}: /{EVENTS_GROUP}/{sensor}/trigger is missing")
        return TriggerEvents(
            np.asarray(tg[TriggerEdges.T][...], dtype=np.int64),
            np.asarray(tg[TriggerEdges.P][...], dtype=np.uint8),
            np.asarray(tg[TriggerEdges.CHANNEL][...], dtype=np.uint8),
        )

    def trigger_host_times(self, sensor: str) -> NDArray[np.int64]:
        """Host monotonic ns at which each trigger-in edge's packet arrived; -1 where unknown.

        Schema 1.0 takes did not record it: all -1 (the same "unknown" a 1.1 writer stores).
        """
        g = self._sensor_group(sensor)
        tg = g.get(Events.TRIGGER)
        if not isinstance(tg, h5py.Group):
            raise TakeFormatError(f"{self.path}: /{EVENTS_GROUP}/{sensor}/trigger is missing")
        n = int(tg[TriggerEdges.T].shape[0])
        if TriggerEdges.HOST_TIME_NS not in tg:
            return np.full(n, -1, np.int64)
        return np.asarray(tg[TriggerEdges.HOST_TIME_NS][:n], dtype=np.int64)

    def pulses(self) -> PulseBatch:
        g = self._f.get(PULSES_PATH)
        if not isinstance(g, h5py.Group):
            raise TakeFormatError(f"{self.path}: /{TRIGGER_GROUP}/pulses is missing")
        return PulseBatch(
            np.asarray(g[Pulses.INDEX][...], dtype=np.int64),
            np.asarray(g[Pulses.T_US][...], dtype=np.int64),
            np.asarray(g[Pulses.HOST_TIME_NS][...], dtype=np.int64),
        )

    def frames(self, camera: str, demosaic: bool = True) -> FrameSeries:
        """One camera's frames; a Bayer camera's demosaiced to RGB unless `demosaic=False`."""
        g = self._f.get(f"{FRAMES_GROUP}/{camera}")
        if not isinstance(g, h5py.Group):
            raise TakeError(f"{self.path}: no camera {camera!r} (has {self.cameras})")
        return FrameSeries(self, camera, g, demosaic)

    def event_span(self, sensor: str) -> tuple[int, int] | None:
        """(first, last) event time in the take's time domain, or None without events."""
        words = self._words(sensor)
        if words is not None:
            return words.span()
        g = self._sensor_group(sensor)
        n = self._n_events(g)
        if n == 0:
            return None
        return int(self._read_events(g, 0, 1, self._offset(sensor)).t[0]), int(
            self._read_events(g, n - 1, n, self._offset(sensor)).t[0]
        )

    # -- summary -----------------------------------------------------------------------
    def summary(self) -> TakeSummary:
        """Counts, rates and sync quality; reads only metadata, first/last times and the report."""
        report = self.sync_report
        devs = report.devices if report else {}
        cams: dict[str, CameraSummary] = {}
        for name in self.cameras:
            fs = self.frames(name, demosaic=False)
            ts = fs.timestamps_us
            fps = (
                (ts.size - 1) / ((int(ts[-1]) - int(ts[0])) / 1e6) if ts.size > 1 and ts[-1] > ts[0] else None
            )
            d = devs.get(name)
            cams[name] = CameraSummary(
                frames=len(fs),
                fps=fps,
                shape=list(fs.stored_shape),
                dtype=str(self._f[f"{FRAMES_GROUP}/{name}/images"].dtype),
                pixel_format=fs.pixel_format,
                t_first_us=int(ts[0]) if ts.size else None,
                t_last_us=int(ts[-1]) if ts.size else None,
                dropped_frames=len(d.dropped_frames) if d else None,
                missing_pulses=len(d.missing_pulses) if d else None,
                sync_rms_us=_finite(d.residual_rms_us) if d else None,
                sync_max_us=_finite(d.residual_max_us) if d else None,
            )
        sens: dict[str, EventSensorSummary] = {}
        for name in self.event_sensors:
            g = self._sensor_group(name)
            n = self._n_events(g)
            span = self.event_span(name)
            span_us = span[1] - span[0] if span else 0
            d = devs.get(name)
            tg = g.get(Events.TRIGGER)
            sens[name] = EventSensorSummary(
                events=n,
                event_rate_hz=n / (span_us / 1e6) if span_us > 0 else None,
                t_first_us=span[0] if span else None,
                t_last_us=span[1] if span else None,
                span_us=span_us,
                width=int(g.attrs.get(Device.WIDTH, 0)),
                height=int(g.attrs.get(Device.HEIGHT, 0)),
                triggers=int(tg[TriggerEdges.T].shape[0])
                if isinstance(tg, h5py.Group) and TriggerEdges.T in tg
                else 0,
                missing_pulses=len(d.missing_pulses) if d else None,
                sync_rms_us=_finite(d.residual_rms_us) if d else None,
                sync_max_us=_finite(d.residual_max_us) if d else None,
            )
        pulses_node = self._f.get(f"{TRIGGER_GROUP}/pulses/index")
        raw_reason = self._f.attrs.get(Root.FAILURE_REASON)
        reason = None if raw_reason is None else attr_text(raw_reason)
        status, recovered = self.status, self.recovered_utc
        verdict = take_verdict(
            status,
            report,
            {k: c.frames for k, c in cams.items()},
            {k: e.events for k, e in sens.items()},
            recovered_utc=recovered,
            failure_reason=reason,
        )
        return TakeSummary(
            path=str(self.path),
            take_id=self.take_id,
            status=status,
            verdict=verdict.verdict,
            verdict_reasons=verdict.reasons,
            schema_version=self.schema_version,
            time_domain=self.time_domain,
            failure_reason=reason,
            recovered_utc=recovered,
            end_reason=self.end_reason,
            cameras=cams,
            event_sensors=sens,
            pulses=int(pulses_node.shape[0]) if isinstance(pulses_node, h5py.Dataset) else 0,
            pulses_seen_by_no_device=list(report.pulses_seen_by_no_device) if report else [],
            losses=list(report.losses) if report else [],
            warnings=list(report.warnings) if report else [],
        )


def open_take(path: str | Path) -> Take:
    """Open a take read-only; raises TakeError naming the file if it cannot."""
    return Take(path)
