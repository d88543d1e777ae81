"""Reading an "evt_words" event sensor: its stored EVT words decoded on demand.

`evt_index` says, per stored block, where its bytes are, how many events it decodes to, its
first and last time and the decoder state to start from. A read finds the blocks a request
overlaps (their times mapped through the sensor's clock map), reads their bytes (`WordBytes`:
the Zstd chunks decompressed here, only as far as needed) and decodes each run of blocks from its
first block's state with the production decoder; a time window stops decoding where the window
ends (decision 0035). Times are not
rewritten at finalize: the reader adds each block's shift and applies the clock map, and clips
to the take window, whose stored events [first_in_window, first_in_window + events_in_window)
finalize counted (`window_range`). Event indices count the events inside the window.
"""

from __future__ import annotations

import itertools
import json
import mmap
import os
from pathlib import Path

import h5py
import numpy as np
import zstandard
from numba import njit
from numpy.typing import NDArray

from rigd.core.errors import TakeFormatError
from rigd.core.events import EventArray
from rigd.core.layout import EVT_INDEX_COLUMNS, Device, Events, Storage
from rigd.core.timebase import ClockMap
from rigd.evt import StreamDecoder, decode_from_state

#: Group attrs finalize writes on an evt_words sensor.
_NHEAD = len(EVT_INDEX_COLUMNS)
#: More events than any EVT format packs into a byte (EVT 3.0's 12-event vector word: 6).
_MAX_EVENTS_PER_BYTE = 8
#: Device us searched beyond a window's edges mapped back to the device clock (to_device
#: rounds, and the rate is within a few hundred ppm of 1), before the exact search in rig time.
_MAP_SLACK_US = 4
#: HDF5 filter id of hdf5plugin's Zstd (the words' chunks): a plain zstd frame per chunk.
_ZSTD_FILTER = 32015
#: A window's last row is first decoded up to where its time interpolates to the window's end,
#: plus this fraction of the row (rows are ~10 ms; events are about even in time within one).
_CUT_MARGIN = 1 / 8
#: Rows `histogram` decodes with one read at most (each at most 1 MiB of words).
_HISTOGRAM_ROWS = 64
#: The largest byte buffer a reader keeps for the next read (a 50 ms window of a 20 Mev/s
#: sensor is ~2.5 MB); longer reads get their own.
_KEEP_BUFFER = 16 << 20


def consistent_rows(rows: NDArray[np.int64], available: int) -> int:
    """Leading rows that follow on from each other (start = previous end, from byte 0, a
    positive length) and end within `available` bytes."""
    n = rows.shape[0]
    if n == 0:
        return 0
    start, length = rows[:, 0], rows[:, 1]
    expect = np.concatenate([[0], (start + length)[:-1]])
    good = (start == expect) & (length > 0) & (start + length <= available)
    bad = np.flatnonzero(~good)
    return int(bad[0]) if bad.size else n


@njit(nogil=True, cache=True)
def _to_rig(t: NDArray[np.int64], dref: int, rref: int, rate: float, frac: float) -> NDArray[np.int64]:
    """`ClockMap.to_rig` of `t`, the same float64 operations in the same order (bit-identical):
    one pass, no temporaries."""
    out = np.empty(t.shape[0], np.int64)
    for i in range(t.shape[0]):
        out[i] = np.int64(np.rint(np.float64(t[i] - dref) * rate + frac)) + rref
    return out


class WordBytes:
    """Byte ranges of an `evt_words` dataset, chunk by chunk: each Zstd chunk is read as stored
    and decompressed by `zstandard` straight into the result, only up to the last byte asked
    for (a zstd frame decodes from its start, so the bytes of the first chunk before the range
    are decoded and dropped). Through h5py every chunk a range touches was decompressed whole
    into the chunk cache and copied out: about a third more work for a 50 ms window. Other
    filter pipelines read through h5py."""

    def __init__(self, ds: h5py.Dataset, where: str, *, mapped: bool = False) -> None:
        self.ds, self.where = ds, where
        dcpl = ds.id.get_create_plist()
        filters = [dcpl.get_filter(i)[0] for i in range(dcpl.get_nfilters())]
        self.chunk = int(ds.chunks[0]) if ds.chunks is not None and ds.ndim == 1 else 0
        self.direct = self.chunk > 0 and filters in ([], [_ZSTD_FILTER])
        self.zstd = filters == [_ZSTD_FILTER]
        self._dctx = zstandard.ZstdDecompressor()
        self._buf = np.empty(0, np.uint8)
        self._lo = self._hi = 0  # the dataset's bytes the buffer holds
        # (chunk, byte, zstd stream) where the last read stopped inside a chunk
        self._live: tuple[int, int, zstandard.ZstdDecompressionReader] | None = None
        self._where_chunk: dict[int, tuple[int, int, int]] = {}  # byte -> (offset, size, mask)
        self._map: mmap.mmap | None = None
        self._map = self._open_map() if mapped and self.direct else None

    def _open_map(self) -> mmap.mmap | None:
        """The file mapped read-only, so that a chunk's stored bytes are decompressed where the
        page cache holds them (`read_direct_chunk` copies them into a new bytes object first:
        ~35 us of a chunk's ~300). Only for a file HDF5 reads itself, unchanged (`sec2`, opened
        read-only, no user block; the caller maps only a take that is no longer written), and
        only when the first chunk reads the same both ways."""
        f = self.ds.file
        if f.driver != "sec2" or f.mode != "r" or f.userblock_size or not self.ds.shape[0]:
            return None
        with open(f.filename, "rb") as fh:
            if os.fstat(fh.fileno()).st_size == 0:
                return None
            m = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
        self._map = m
        try:
            same = bytes(self._stored(0)[1]) == self.ds.id.read_direct_chunk((0,))[1]
        except RuntimeError:  # chunk 0 never written: nothing to compare with
            same = False
        self._where_chunk.clear()
        if not same:
            m.close()
            return None
        return m

    def _stored(self, c0: int) -> tuple[int, bytes | memoryview]:
        """(filter mask, stored bytes) of the chunk at byte c0: from the mapped file when the
        chunk lies inside it, else (and for a chunk never written) as HDF5 reads it."""
        m = self._map
        if m is not None:
            loc = self._where_chunk.get(c0)
            if loc is None:
                info = self.ds.id.get_chunk_info_by_coord((c0,))
                off = info.byte_offset
                if off is not None and off + info.size <= len(m):
                    loc = self._where_chunk[c0] = (int(off), int(info.size), int(info.filter_mask))
            if loc is not None:
                return loc[2], memoryview(m)[loc[0] : loc[0] + loc[1]]
        mask, raw = self.ds.id.read_direct_chunk((c0,))
        return int(mask), raw

    def read(self, a: int, b: int) -> NDArray[np.uint8]:
        """Bytes [a, b) of the dataset (b at most its length). Valid until the next call: the
        bytes live in one buffer the reader keeps (no fresh pages per window), which holds the
        dataset's bytes [lo, hi) from a chunk's start on. A read that starts in a chunk the
        buffer already holds goes on from there (its zstd stream too, when the last read
        stopped inside a chunk): windows read in order, or a read that finishes a row the
        last one cut short, decompress nothing twice."""
        if not self.direct or b <= a or not self.ds.id.valid:  # a closed take: h5py says so
            return np.asarray(self.ds[a:b], dtype=np.uint8)
        first = a - a % self.chunk  # a chunk is decoded from its start, into the buffer too
        if not self._lo <= first < self._hi:
            self._lo = self._hi = first
            self._live = None
        elif b <= self._hi:
            return self._buf[a - self._lo : b - self._lo]
        if b - self._lo > self._buf.shape[0]:
            kept = self._buf[first - self._lo : self._hi - self._lo]
            if b - first > _KEEP_BUFFER:  # a long read: its own buffer, nothing kept after it
                buf = np.empty(b - first, np.uint8)
                buf[: kept.shape[0]] = kept
                self._fill(buf, first, self._hi, b)
                self._lo = self._hi = 0
                self._live = None
                return buf[a - first :]
            if b - first > self._buf.shape[0]:
                grown = np.empty(min(max(b - first, 2 * self._buf.shape[0]), _KEEP_BUFFER), np.uint8)
                grown[: kept.shape[0]] = kept
                self._buf = grown
            else:
                self._buf[: kept.shape[0]] = kept.copy()
            self._lo = first
        self._fill(self._buf, self._lo, self._hi, b)
        self._hi = b
        return self._buf[a - self._lo : b - self._lo]

    def _fill(self, buf: NDArray[np.uint8], base: int, pos: int, b: int) -> None:
        """Bytes [pos, b) into buf (whose byte 0 is the dataset's byte `base`), chunk by chunk;
        a chunk begun before `pos` goes on from the zstd stream left there."""
        size = self.chunk
        while pos < b:
            c0 = pos - pos % size
            hi = min(c0 + size, b)
            dst = buf[pos - base : hi - base]
            live, self._live = self._live, None
            if live is not None and live[0] == c0 and live[1] == pos:
                reader = live[2]
            else:
                try:
                    mask, raw = self._stored(c0)
                except RuntimeError:
                    if self.ds.id.get_chunk_info_by_coord((c0,)).byte_offset is not None:
                        raise
                    # never written (a damaged take): what h5py reads there, the fill value
                    dst[:] = self.ds[pos:hi]
                    pos = hi
                    continue
                if not self.zstd or mask & 1:  # stored as it is (writer behind, decision 0021)
                    dst[:] = np.frombuffer(raw, np.uint8, count=hi - c0)[pos - c0 :]
                    pos = hi
                    continue
                reader = self._dctx.stream_reader(raw)
                if pos > c0:  # begun, its stream not kept: again from the chunk's start
                    dst = buf[c0 - base : hi - base]
            self._inflate(reader, dst, c0)
            if hi < c0 + size:
                self._live = (c0, hi, reader)
            pos = hi

    def _inflate(self, reader: zstandard.ZstdDecompressionReader, dst: NDArray[np.uint8], c0: int) -> None:
        """The next len(dst) bytes of the zstd stream of the chunk at byte c0."""
        view, got = dst.data, 0
        try:
            while got < dst.shape[0]:
                k = reader.readinto(view[got:])
                if k <= 0:
                    break
                got += k
        except zstandard.ZstdError as exc:
            raise TakeFormatError(
                f"{self.where}/{Events.EVT_WORDS}: the chunk at byte {c0} does not decompress ({exc})"
            ) from exc
        if got < dst.shape[0]:
            raise TakeFormatError(
                f"{self.where}/{Events.EVT_WORDS}: the chunk at byte {c0} decompresses to fewer bytes "
                f"than its share of the dataset (damaged chunk)"
            )


def is_evt_words(g: h5py.Group) -> bool:
    """Whether an event sensor group stores EVT words (schema 1.2) rather than x/y/p/t."""
    value = g.attrs.get(Events.STORAGE, Storage.COLUMNS)
    return (value.decode() if isinstance(value, bytes) else str(value)) == Storage.EVT_WORDS


def clock_map_json(cmap: ClockMap) -> str:
    """The map as finalize stores it (floats written with repr: read back bit-exact)."""
    return json.dumps([cmap.device_ref_us, cmap.rig_ref_us, cmap.rate, cmap.frac_us])


class EvtWordsEvents:
    """One evt_words sensor of an open take. `cmap` None: times stay in the device clock (a
    take never finalized); `window` (rig us, either bound None) clips what is shown."""

    def __init__(
        self,
        g: h5py.Group,
        where: str | Path,
        cmap: ClockMap | None,
        window: tuple[int | None, int | None] = (None, None),
        *,
        with_tail: bool = False,
    ) -> None:
        self.where = f"{where}: {g.name}"
        self.g = g
        fmt = g.attrs[Events.EVT_FORMAT]
        self.fmt = fmt.decode() if isinstance(fmt, bytes) else str(fmt)
        self.width, self.height = int(g.attrs[Device.WIDTH]), int(g.attrs[Device.HEIGHT])
        self.words: h5py.Dataset = g[Events.EVT_WORDS]
        idx = np.asarray(g[Events.EVT_INDEX][...], dtype=np.int64).reshape(-1, g[Events.EVT_INDEX].shape[1])
        self.start, self.length, self.count = idx[:, 0], idx[:, 1], idx[:, 2]
        self.shift = idx[:, 5]
        self.follows = idx[:, 6]
        self.states = idx[:, _NHEAD:]
        self.cum = np.concatenate([[0], np.cumsum(self.count)]).astype(np.int64)
        self.cmap = cmap
        self.first_device, self.last_device = idx[:, 3], idx[:, 4]
        self.first = self._map(self.first_device)
        self.last = self._map(self.last_device)
        self._bytes = WordBytes(self.words, self.where, mapped=not with_tail)
        self.lo, self.hi = window
        self._tail = self._tail_bytes() if with_tail else None
        self._check_index(idx)
        if Events.FIRST_IN_WINDOW in g.attrs and cmap is not None:
            self.i0 = int(g.attrs[Events.FIRST_IN_WINDOW])
            self.i1 = self.i0 + int(g.attrs[Events.EVENTS_IN_WINDOW])
        else:
            self.i0, self.i1 = self.window_range()

    def _check_index(self, idx: NDArray[np.int64]) -> None:
        """Refuse an index whose rows do not follow on within the stored bytes, or say more
        events than their bytes can hold: every read sizes its buffers from these rows, so a
        damaged or hostile row must not reach one (a length of 2**31 asked for 2 GB)."""
        tail = self._tail
        available = int(self.words.shape[0]) if tail is None else tail[0] + len(tail[1])
        good = consistent_rows(idx, available)
        if good < idx.shape[0]:
            r = idx[good]
            raise TakeFormatError(
                f"{self.where}/{Events.EVT_INDEX}: row {good} (start {int(r[0])}, length {int(r[1])}) does "
                f"not follow on from the row before or ends past the {available} stored bytes"
            )
        bad = np.flatnonzero((self.count < 0) | (self.count > _MAX_EVENTS_PER_BYTE * self.length))
        if bad.size:
            r = int(bad[0])
            raise TakeFormatError(
                f"{self.where}/{Events.EVT_INDEX}: row {r} says {int(self.count[r])} events in "
                f"{int(self.length[r])} bytes (at most {_MAX_EVENTS_PER_BYTE} an EVT byte holds)"
            )

    @property
    def stored(self) -> int:
        return int(self.cum[-1])

    def __len__(self) -> int:
        return self.i1 - self.i0

    def _map(self, t: NDArray[np.int64]) -> NDArray[np.int64]:
        return t if self.cmap is None else self.cmap.to_rig(t)

    def _tail_bytes(self) -> tuple[int, NDArray[np.uint8]] | None:
        """(first byte, bytes) of the flushed tail slot that ends furthest (unfinished take)."""
        ds = self.g.get(Events.TAIL_WORDS)
        if not isinstance(ds, h5py.Dataset) or Events.TAIL_WORDS_META not in self.g.attrs:
            return None
        meta = np.asarray(self.g.attrs[Events.TAIL_WORDS_META], dtype=np.int64).reshape(-1, 2)
        slot = int(np.argmax(meta[:, 0] + meta[:, 1]))
        start, n = int(meta[slot, 0]), int(meta[slot, 1])
        return (start, np.asarray(ds[slot, :n], dtype=np.uint8)) if n else None

    def stored_bytes(self, a: int, b: int) -> NDArray[np.uint8]:
        tail = self._tail
        if tail is None or b <= tail[0]:
            return self._bytes.read(a, b)
        head = self._bytes.read(a, tail[0]) if a < tail[0] else np.empty(0, np.uint8)
        return np.concatenate([head, tail[1][max(a - tail[0], 0) : b - tail[0]]])

    # -- decoding ----------------------------------------------------------------------
    def to_rig(self, t: NDArray[np.int64]) -> NDArray[np.int64]:
        """Device us (shift included) to rig us with the sensor's clock map (compiled, exact)."""
        c = self.cmap
        assert c is not None
        return _to_rig(np.ascontiguousarray(t), c.device_ref_us, c.rig_ref_us, c.rate, c.frac_us)

    def decode_rows(self, r0: int, r1: int) -> EventArray:
        """All stored events of rows [r0, r1), in the reader's time domain (one byte read)."""
        ev = self._decode_device(r0, r1)
        return ev if self.cmap is None else ev.with_time(self.to_rig(ev.t))

    def _cut(self, r: int, stop: int) -> int:
        """A byte of row r past which the row's events are at or after device time `stop`, by
        their times being about even in the row, with a margin; the row's end when unsure."""
        first, last = int(self.first_device[r]), int(self.last_device[r])
        start, length = int(self.start[r]), int(self.length[r])
        if stop > last:
            return start + length
        frac = max(stop - first, 0) / (last - first + 1)
        return start + min(length, max(int(length * (frac + _CUT_MARGIN)) + 64, 0))

    def _decode_device(self, r0: int, r1: int, stop: int | None = None) -> EventArray:
        """Rows [r0, r1) decoded, times in the device clock (their shifts added): each run of
        rows that follow on in the stream with one decoder from its first row's state. `stop`
        (device us, shifts included): the events at or after it are not needed (a window's
        end), so the last row is read and decoded only as far as its events reach it (`_cut`)."""
        if r1 <= r0:
            return EventArray.empty()
        base = int(self.start[r0])
        end = int(self.start[r1 - 1] + self.length[r1 - 1])
        cut = end if stop is None else self._cut(r1 - 1, stop)
        data = self.stored_bytes(base, cut)
        breaks = [r0, *(r0 + 1 + np.flatnonzero(self.follows[r0 + 1 : r1] == 0)).tolist(), r1]
        parts = []
        for a, b in itertools.pairwise(breaks):
            lo, hi = int(self.start[a]) - base, int(self.start[b - 1] + self.length[b - 1]) - base
            shift = int(self.shift[a])
            whole = base + hi <= cut
            if whole:
                ev = decode_from_state(self.fmt, data[lo:hi], self.states[a], self.width, self.height)
            else:  # the last run, cut short
                ev, whole = self._decode_until(a, data[lo:], int(stop or 0) - shift, cut, base + hi)
            want = int(self.cum[b] - self.cum[a])
            if len(ev) != want and (whole or len(ev) > want):
                raise TakeFormatError(
                    f"{self.where}/{Events.EVT_INDEX}: rows [{a}, {b}) decode to {len(ev)} events, the index "
                    f"says {want} (damaged words or index)"
                )
            parts.append(ev.with_time(ev.t + shift) if shift else ev)
        return parts[0] if len(parts) == 1 else EventArray.concatenate(parts)

    def _decode_until(
        self, r: int, head: NDArray[np.uint8], stop: int, cut: int, end: int
    ) -> tuple[EventArray, bool]:
        """The events of the run starting at row r (bytes up to `end`, of which `head` holds
        those up to `cut`), and whether they are all of its events. Decoding stops at the cut
        when an event at or after `stop` (device us, the run's shift not included) is among
        those decoded: the rest come later in the stream and time never decreases in it (the
        words the decoder holds back at the cut are such later ones). Else the rest is read
        and decoded too."""
        dec = StreamDecoder(self.fmt, width=self.width, height=self.height, state=self.states[r])
        ev = dec.feed(head).events
        if len(ev) and int(ev.t[-1]) >= stop:
            return ev, False
        more = dec.feed(self.stored_bytes(cut, end)).events
        held = dec.flush().events
        return EventArray.concatenate([p for p in (ev, more, held) if len(p)] or [ev]), True

    def _stored_index(self, t: int) -> int:
        """Stored index of the first event at or after t (reader's time domain)."""
        r = int(np.searchsorted(self.last, t, side="left"))
        if r >= self.last.shape[0]:
            return self.stored
        ev = self.decode_rows(r, r + 1)
        return int(self.cum[r]) + int(np.searchsorted(ev.t, t, side="left"))

    def window_range(self) -> tuple[int, int]:
        """Stored events [i0, i1) inside the take window; decodes at most the two edge rows."""
        i0 = 0 if self.lo is None else self._stored_index(self.lo)
        i1 = self.stored if self.hi is None else self._stored_index(self.hi)
        return i0, max(i0, i1)

    # -- what the reader asks ----------------------------------------------------------
    def by_index(self, a: int, b: int) -> EventArray:
        """Events [a, b) counted inside the window."""
        n = len(self)
        a, b = max(0, min(a, n)), max(0, min(b, n))
        if b <= a:
            return EventArray.empty()
        sa, sb = a + self.i0, b + self.i0
        r0 = int(np.searchsorted(self.cum, sa, side="right")) - 1
        r1 = int(np.searchsorted(self.cum, sb, side="left"))
        ev = self.decode_rows(r0, r1)
        off = int(self.cum[r0])
        return ev[sa - off : sb - off]

    def index_at(self, t: int) -> int:
        """Index (inside the window) of the first event at or after t."""
        return min(max(self._stored_index(t), self.i0), self.i1) - self.i0

    def window(self, t0: int, t1: int) -> EventArray:
        """Events with t0 <= t < t1 inside the take window: the overlapping rows decoded once."""
        if self.lo is not None:
            t0 = max(t0, self.lo)
        if self.hi is not None:
            t1 = min(t1, self.hi)
        if t1 <= t0:
            return EventArray.empty()
        r0 = int(np.searchsorted(self.last, t0, side="left"))
        r1 = int(np.searchsorted(self.first, t1, side="left"))
        if self.cmap is None:
            ev = self._decode_device(r0, max(r0, r1), stop=t1)
            i = int(np.searchsorted(ev.t, t0, side="left"))
            return ev[i : max(i, int(np.searchsorted(ev.t, t1, side="left")))]
        # map only the events near the window: the map is monotonic, its inverse exact to 1 us
        # (`ClockMap.to_device` in Python floats: the same IEEE operations, no arrays for two)
        c = self.cmap
        d0, d1 = (round((float(t - c.rig_ref_us) - c.frac_us) / c.rate) + c.device_ref_us for t in (t0, t1))
        ev = self._decode_device(r0, max(r0, r1), stop=d1 + _MAP_SLACK_US)
        a = int(ev.t.searchsorted(d0 - _MAP_SLACK_US, side="left"))
        b = int(ev.t.searchsorted(d1 + _MAP_SLACK_US, side="left"))
        rig = self.to_rig(ev.t[a:b])
        i = int(rig.searchsorted(t0, side="left"))
        j = max(i, int(rig.searchsorted(t1, side="left")))
        return EventArray(ev.x[a + i : a + j], ev.y[a + i : a + j], ev.p[a + i : a + j], rig[i:j])

    def span(self) -> tuple[int, int] | None:
        n = len(self)
        if n == 0:
            return None
        return int(self.by_index(0, 1).t[0]), int(self.by_index(n - 1, n).t[0])

    def histogram(self, origin: int, bin_us: int) -> tuple[int, NDArray[np.int64]]:
        """Events per bin aligned to `origin`, first to last event: rows inside one bin are
        counted from the index, rows across a bin edge or the window's edge are decoded."""
        span = self.span()
        if span is None:
            return origin, np.zeros(0, np.int64)
        k0, k1 = (span[0] - origin) // bin_us, (span[1] - origin) // bin_us + 1
        counts = np.zeros(k1 - k0, np.int64)
        r0 = int(np.searchsorted(self.cum, self.i0, side="right")) - 1
        r1 = int(np.searchsorted(self.cum, self.i1, side="left"))
        rows = np.arange(r0, r1)
        bf = (self.first[rows] - origin) // bin_us - k0
        bl = (self.last[rows] - origin) // bin_us - k0
        edge = (rows == r0) | (rows == r1 - 1)
        whole = (bf == bl) & ~edge & (bf >= 0) & (bf < counts.size)
        np.add.at(counts, bf[whole], self.count[rows[whole]])
        # the rows to decode, a run of neighbours with one read (a chunk is decompressed from
        # its start, so row by row would decompress each chunk's first bytes again and again)
        need = rows[~whole & (self.count[rows] > 0)]
        cuts = np.flatnonzero((np.diff(need) != 1) | (np.arange(1, need.size) % _HISTOGRAM_ROWS == 0)) + 1
        for run in np.split(need, cuts) if need.size else []:
            a, b = int(run[0]), int(run[-1]) + 1
            ev = self.decode_rows(a, b)
            lo = max(self.i0 - int(self.cum[a]), 0)
            hi = min(self.i1 - int(self.cum[a]), len(ev))
            k = (ev.t[lo:hi] - origin) // bin_us - k0
            counts += np.bincount(k[(k >= 0) & (k < counts.size)], minlength=counts.size)
        return origin + k0 * bin_us, counts
