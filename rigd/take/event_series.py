"""One event sensor's events in a take: `Take.sensor` returns an EventSeries.

The counterpart of `FrameSeries` for a camera, with one window reader, `events(t0, t1)` (what
DSEC's `EventSlicer.get_events` answers from an exported file). Nothing here loads a whole
event dataset unless asked for all of it: a time window is narrowed with the DSEC `ms_to_idx`
index to the events of the milliseconds it touches, whose `t` is read once and searched for
both edges; `x, y, p` are then read for exactly the window. The series holds its datasets open
for the Take's life (the Take gives out one EventSeries per sensor), so a read costs no lookups
and HDF5 decodes only the chunks the window overlaps (random training windows:
docs/take-format.md). A sensor stored as EVT words (schema 1.2) is decoded on read
(`EvtWordsEvents`); every method answers the same for either storage.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass

import h5py
import numpy as np
from numpy.typing import NDArray

from rigd.core.errors import TakeError, TakeFormatError
from rigd.core.events import EventArray, TriggerEvents
from rigd.core.layout import (
    EVENT_DTYPES,
    EVENTS_GROUP,
    Device,
    Events,
    Status,
    Storage,
    TimeDomain,
    TriggerEdges,
)
from rigd.core.timebase import ClockMap
from rigd.take.evt_read import EvtWordsEvents, is_evt_words
from rigd.take.guard import OpenTake, format_errors
from rigd.take.h5file import attr_text
from rigd.take.tails import tail_rows

#: Events read per step by `EventSeries.iter` (bounded memory, few HDF5 calls).
_READ_BLOCK = 1 << 20
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


@format_errors
class EventSeries:
    """The events of one event sensor; read on request, by time window or by position.

    Times are rig us once the take is finalized; a take never finalized answers the reads that
    need no time (`events()` without bounds, `by_index`, `count`, `span`) in the device clock
    and refuses the others. Valid while its Take is open, like a `FrameSeries`.
    """

    def __init__(self, take: OpenTake, name: str, group: h5py.Group) -> None:
        self._take = take
        self.name = name
        self._g = group
        self._where = f"/{EVENTS_GROUP}/{name}"
        self._t_offset: int | None = None
        self._columns: _EventColumns | None = None
        self._evt: EvtWordsEvents | None = None
        self._evt_read = False

    def _where_file(self) -> str:
        return f"{self._take.path}: {self._where}"

    def __repr__(self) -> str:
        return f"EventSeries({str(self._take.path)!r}, {self.name!r})"

    # -- what the sensor is ------------------------------------------------------------
    @property
    def geometry(self) -> tuple[int, int]:
        """(width, height) of the sensor."""
        return int(self._g.attrs[Device.WIDTH]), int(self._g.attrs[Device.HEIGHT])

    @property
    def storage(self) -> str:
        """How the events are stored: `columns` (x/y/p/t, DSEC) or `evt_words` (schema 1.2)."""
        return Storage.EVT_WORDS if is_evt_words(self._g) else Storage.COLUMNS

    @property
    def evt_format(self) -> str | None:
        """The EVT format the sensor sent (e.g. `evt3`), when it sent EVT words; else None."""
        value = self._g.attrs.get(Events.EVT_FORMAT)
        return None if value is None else attr_text(value)

    @property
    def t_offset(self) -> int:
        """Rig us the stored `t` counts from (DSEC's `t_offset`; 0 before finalize)."""
        if self._t_offset is None:
            g = self._g
            self._t_offset = int(g[Events.T_OFFSET][()]) if Events.T_OFFSET in g else 0
        return self._t_offset

    # -- how many, and when ------------------------------------------------------------
    def __len__(self) -> int:
        return self.count

    @property
    def count(self) -> int:
        """Number of events (those inside the take window for EVT words)."""
        words = self._words()
        if words is not None:
            return len(words)
        n, _, m = self._tail()
        return n + m

    @property
    def span(self) -> tuple[int, int] | None:
        """(first, last) event time in the take's time domain, or None without events."""
        words = self._words()
        if words is not None:
            return words.span()
        n = self.count
        if n == 0:
            return None
        return int(self._read_events(0, 1).t[0]), int(self._read_events(n - 1, n).t[0])

    # -- reads -------------------------------------------------------------------------
    def events(self, t_start_us: int | None = None, t_end_us: int | None = None) -> EventArray:
        """Events with t_start_us <= t < t_end_us (rig us); no bounds returns all of them.

        Without bounds this also works on a never-finalized take (times then in device clock).
        """
        words = self._words()
        if words is not None and (t_start_us is None or t_end_us is None):
            if t_start_us is None and t_end_us is None:
                return words.by_index(0, len(words))
            lo, hi = self._index_range(t_start_us, t_end_us)
            return words.by_index(lo, hi)
        if t_start_us is None and t_end_us is None:
            return self._read_events(0, self.count)
        if t_start_us is not None and t_end_us is not None:
            return self._window(t_start_us, t_end_us)
        lo, hi = self._index_range(t_start_us, t_end_us)
        return self._read_events(lo, hi)

    def by_index(self, start: int, stop: int) -> EventArray:
        """Events [start, stop) by position; works in either time domain."""
        words = self._words()
        if words is not None:
            return words.by_index(start, stop)
        n = self.count
        lo, hi = max(0, min(start, n)), max(0, min(stop, n))
        return self._read_events(lo, max(lo, hi))

    def index(self, t_us: int) -> int:
        """Index of the first event at or after rig time `t_us` (the event count if none), for
        reading on from there in blocks with `by_index`."""
        return self._index_range(int(t_us), None)[0]

    def histogram(self, bin_us: int = 10_000) -> tuple[int, NDArray[np.int64]]:
        """Events per bin of `bin_us` (a multiple of 1 ms), from the ms index alone: a training
        job weighs windows by activity without reading the events. Returns the rig time of bin
        0's start and the counts; bins are aligned to `t_offset` and cover first to last event.
        """
        if bin_us <= 0 or bin_us % 1000:
            raise TakeError(f"{self._take.path}: bin_us must be a positive multiple of 1000, got {bin_us}")
        words = self._words(rig=True)
        if words is not None:
            return words.histogram(self.t_offset, bin_us)
        c, ms_to_idx = self._rig_columns()
        n, off = c.n, self.t_offset
        if n == 0:
            return off, np.zeros(0, np.int64)
        k0, k1 = int(c.t[0]) // bin_us, int(c.t[n - 1]) // bin_us + 1
        edges = np.arange(k0, k1 + 1, dtype=np.int64) * bin_us  # relative to t_offset
        idx = np.full(edges.size, n, np.int64)
        n_ms, step = int(ms_to_idx.shape[0]), bin_us // 1000
        ms = edges // 1000
        on = (edges >= 0) & (ms < n_ms)
        if on.any():
            a, b = int(ms[on][0]), int(ms[on][-1])
            idx[on] = np.asarray(ms_to_idx[a : b + 1 : step], dtype=np.int64)
        neg = edges < 0  # before t_offset (the events before the first pulse): search their t
        if neg.any():
            before = int(ms_to_idx[0]) if n_ms else n
            idx[neg] = np.searchsorted(np.asarray(c.t[:before], dtype=np.int64), edges[neg], side="left")
        return off + k0 * bin_us, np.diff(idx)

    def iter(
        self, window_us: int, t_start_us: int | None = None, t_end_us: int | None = None
    ) -> Iterator[EventArray]:
        """Consecutive windows [t0 + k*w, t0 + (k+1)*w) (possibly empty) up to the last event.

        t0 defaults to the first event. Reads sequentially in large blocks, so iterating a
        whole take costs about one pass over the file.
        """
        if window_us <= 0:
            raise TakeError(f"{self._take.path}: window_us must be positive, got {window_us}")
        self._take.require_rig(self._where)
        span = self.span
        if span is None:
            return
        start = span[0] if t_start_us is None else int(t_start_us)
        end = span[1] + 1 if t_end_us is None else int(t_end_us)
        pos, stop = self._index_range(start, end)
        buf = EventArray.empty()
        w0 = start
        while w0 < end:
            w1 = min(w0 + int(window_us), end)
            while pos < stop and (len(buf) == 0 or int(buf.t[-1]) < w1):
                nxt = min(pos + _READ_BLOCK, stop)
                buf = EventArray.concatenate([buf, self.by_index(pos, nxt)])
                pos = nxt
            k = int(np.searchsorted(buf.t, w1, side="left"))
            yield buf[:k]
            buf = buf[k:]
            w0 = w1

    # -- trigger-in --------------------------------------------------------------------
    def _trigger_group(self) -> h5py.Group:
        tg = self._g.get(Events.TRIGGER)
        if not isinstance(tg, h5py.Group):
            raise TakeFormatError(f"{self._take.path}: {self._where}/trigger is missing")
        return tg

    @property
    def triggers(self) -> TriggerEvents:
        """Trigger-in edges of the sensor (rig time once finalized; device time in `t_device`)."""
        tg = self._trigger_group()
        return TriggerEvents(
            np.asarray(tg[TriggerEdges.T][...], dtype=np.int64),
            np.asarray(tg[TriggerEdges.P][...], dtype=np.uint8),
            np.asarray(tg[TriggerEdges.CHANNEL][...], dtype=np.uint8),
        )

    @property
    def trigger_count(self) -> int:
        """Number of trigger-in edges (0 where the sensor has no trigger group)."""
        tg = self._g.get(Events.TRIGGER)
        return int(tg[TriggerEdges.T].shape[0]) if isinstance(tg, h5py.Group) and TriggerEdges.T in tg else 0

    @property
    def trigger_host_times(self) -> NDArray[np.int64]:
        """Host monotonic ns at which each trigger-in edge's packet arrived; -1 where unknown.

        Schema 1.0 takes did not record it: all -1 (the same "unknown" a 1.1 writer stores).
        """
        tg = self._trigger_group()
        n = int(tg[TriggerEdges.T].shape[0])
        if TriggerEdges.HOST_TIME_NS not in tg:
            return np.full(n, -1, np.int64)
        return np.asarray(tg[TriggerEdges.HOST_TIME_NS][:n], dtype=np.int64)

    # -- storage -----------------------------------------------------------------------
    def _words(self, *, rig: bool = False) -> EvtWordsEvents | None:
        """The sensor's stored EVT words (None: it stores x/y/p/t columns); `rig`: refuse a
        take never finalized (its times are still in the device clock)."""
        if not self._evt_read:
            g, take = self._g, self._take
            if is_evt_words(g):
                cmap_text = g.attrs.get(Events.CLOCK_MAP) if take.time_domain == TimeDomain.RIG else None
                cmap = None if cmap_text is None else ClockMap(*json.loads(attr_text(cmap_text)))
                lo, hi = json.loads(attr_text(g.attrs.get(Events.WINDOW, "[null, null]")))
                self._evt = EvtWordsEvents(
                    g, take.path, cmap, (lo, hi), with_tail=take.status == Status.RECORDING
                )
            self._evt_read = True
        words = self._evt
        if words is not None and rig and words.cmap is None:
            self._take.require_rig(self._where)
        return words

    def _tail(self) -> tuple[int, int, int]:
        """(main rows, tail slot, tail rows). A take whose writer died before `rigd recover`
        keeps the flushed events past its last whole chunk in `tail_*` (see
        docs/take-format.md); index reads include them."""
        g = self._g
        n = int(g[Events.T].shape[0])
        if self._take.status != Status.RECORDING or Events.TAIL_META not in g.attrs:
            return n, 0, 0
        slot, m = tail_rows(g, n)
        return n, slot, m

    def _cols(self) -> _EventColumns:
        if self._columns is None:
            g = self._g
            ms = g.get(Events.MS_TO_IDX)
            ms_to_idx = ms if isinstance(ms, h5py.Dataset) else None
            self._columns = _EventColumns(g[Events.X], g[Events.Y], g[Events.P], g[Events.T], ms_to_idx)
        return self._columns

    def _rig_columns(self) -> tuple[_EventColumns, h5py.Dataset]:
        """The column handles and the ms index, for a time query (which needs rig time)."""
        self._take.require_rig(self._where)
        c = self._cols()
        if c.ms_to_idx is None:
            raise TakeFormatError(f"{self._take.path}: {self._where}/{Events.MS_TO_IDX} is missing")
        return c, c.ms_to_idx

    def _read_events(self, lo: int, hi: int) -> EventArray:
        n, slot, m = self._tail()
        main = self._read_main(lo, min(hi, n))
        if hi <= n or m == 0:
            return main
        a, b = max(lo, n) - n, min(hi, n + m) - n
        g = self._g
        cols = {k: np.asarray(g[f"{Events.TAIL_PREFIX}{k}"][slot, a:b]) for k in EVENT_DTYPES}
        tail = EventArray(
            cols[Events.X].astype(np.uint16),
            cols[Events.Y].astype(np.uint16),
            cols[Events.P].astype(np.int8) * np.int8(2) - np.int8(1),
            cols[Events.T].astype(np.int64) + np.int64(self.t_offset),
        )
        return EventArray.concatenate([main, tail])

    def _read_main(self, lo: int, hi: int, t_rel: NDArray[np.int64] | None = None) -> EventArray:
        """Events [lo, hi) of the main datasets; `t_rel`: their `t`, when already read."""
        c = self._cols()
        hi = max(lo, hi)
        t = np.asarray(c.t[lo:hi] if t_rel is None else t_rel, dtype=np.int64) + np.int64(self.t_offset)
        p = np.asarray(c.p[lo:hi]).astype(np.int8) * np.int8(2) - np.int8(1)
        x = np.asarray(c.x[lo:hi], dtype=np.uint16)
        return EventArray(x, np.asarray(c.y[lo:hi], dtype=np.uint16), p, t)

    def _first_index(self, ms_to_idx: h5py.Dataset, rel: int, n: int) -> int:
        """First event index with t (relative to t_offset) >= rel: ms_to_idx bracket, then search."""
        lo, hi = _ms_bracket(ms_to_idx, rel, n)
        if lo >= hi:
            return lo
        return lo + int(np.searchsorted(self._cols().t[lo:hi], rel, side="left"))

    def _window(self, t_start_us: int, t_end_us: int) -> EventArray:
        """Events with t_start_us <= t < t_end_us: `t` of the window's ms bracket is read once
        and searched for both edges, `x, y, p` only for the window itself."""
        words = self._words(rig=True)
        if words is not None:
            return words.window(int(t_start_us), int(t_end_us))
        c, ms = self._rig_columns()
        off, n = self.t_offset, c.n
        rel0, rel1 = int(t_start_us) - off, max(int(t_end_us), int(t_start_us)) - off
        lo, _ = _ms_bracket(ms, rel0, n)
        _, hi = _ms_bracket(ms, rel1, n)
        if hi - lo > _WINDOW_T_MAX:  # a long span: search each edge's bracket on its own
            i, j = self._first_index(ms, rel0, n), self._first_index(ms, rel1, n)
            return self._read_main(i, max(i, j))
        t = np.asarray(c.t[lo:hi], dtype=np.int64)
        i = int(np.searchsorted(t, rel0, side="left"))
        j = max(i, int(np.searchsorted(t, rel1, side="left")))
        return self._read_main(lo + i, lo + j, t[i:j])

    def _index_range(self, t_start_us: int | None, t_end_us: int | None) -> tuple[int, int]:
        words = self._words(rig=True)
        if words is not None:
            lo = 0 if t_start_us is None else words.index_at(int(t_start_us))
            return lo, max(lo, len(words) if t_end_us is None else words.index_at(int(t_end_us)))
        c, ms = self._rig_columns()
        n, off = c.n, self.t_offset
        lo = 0 if t_start_us is None else self._first_index(ms, int(t_start_us) - off, n)
        hi = n if t_end_us is None else self._first_index(ms, int(t_end_us) - off, n)
        return lo, max(lo, hi)
