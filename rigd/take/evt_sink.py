"""The event sink of sensors that send an EVT stream: their words stored as sent.

`/events/<name>/evt_words` holds the bytes (256 KiB chunks, Zstd level 1 through hdf5plugin's
filter, so plain h5py reads them back); the writer compresses each whole chunk itself with
`zstandard` (which releases the GIL) and hands it to HDF5 with `write_direct_chunk`, so storing
an event costs about a memcpy and no HDF5 call per batch. While the writer is behind, whole
chunks are stored uncompressed instead (`compress`; HDF5's per-chunk filter mask says so and
readers skip the decompression). `evt_index` has one row per stored
block: where its bytes are, its event count and first/last device time, the time shift a
re-tied clock gave it, and the decoder state to decode it from (`StreamDecoder(state=...)`).
Chunks that continue each other are merged into one row while it is under `ROW_BYTES`, so a
reader decodes about a millisecond of data beyond what it asked for.

Crash safety is that of the column sink: the main dataset only ever receives whole chunks
while recording; a flush puts the partial last chunk into one of two fixed, unfiltered tail
slots (`tail_evt_words`, attr `tail_words_meta`: [first byte, bytes held] per slot, chosen as
`rigd.take.tails` does), and `rigd.take.evt_repair` merges it back after a kill.
"""

from __future__ import annotations

import errno
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Self

import h5py
import hdf5plugin
import numpy as np
import zstandard
from numpy.typing import NDArray

from rigd.core.errors import TakeError, TakeFormatError, WriteDeferredError
from rigd.core.events import EventPacket, EventSpan, EvtChunk, TriggerEvents
from rigd.core.layout import (
    EVENTS_GROUP,
    EVT_INDEX_COLUMNS,
    TRIGGER_DTYPES,
    Device,
    Events,
    Storage,
    TriggerEdges,
)
from rigd.evt import StreamDecoder
from rigd.take.h5file import append_rows, chunk_is_stored, require_dataset, require_group, write_chunk
from rigd.take.sinks import DeviceWriteStats, TriggerIn, check_event_batch, new_series
from rigd.take.tails import choose_tail_slot

if TYPE_CHECKING:
    from rigd.core.events import EventArray
    from rigd.core.timebase import ClockMap
    from rigd.take.finalize import Finalizer

#: Bytes per chunk of evt_words: the unit compressed and written at once, and what a read
#: decompresses beyond its bytes. 256 KiB stores as small as 1 MiB (2.37 B/ev on the real Gen4.1
#: stream at 64 KiB..1 MiB alike) and decompresses a quarter as much per random window.
WORDS_CHUNK = 256 << 10
#: evt_words is grown this many chunks (64 MiB) at a time (its extent runs ahead of the data;
#: the index says where the data ends), so appending is not a resize per chunk.
_GROW_CHUNKS = 256
#: A row of evt_index stops growing at this many bytes (about 1 ms at 20 Mev/s): what a reader
#: decodes beyond a window's edge.
ROW_BYTES = 128 << 10
#: ... or once it spans this many us (a slow sensor's rows stay short in time too: a window's
#: edges then decode a packet or so beyond it, not 128 KiB of a 1 Mev/s stream, ~40 ms).
ROW_US = 2000
#: Rows per chunk of evt_index.
_INDEX_CHUNK = 1024
_ZSTD_LEVEL = 1
#: HDF5 filter mask of a chunk stored without the Zstd filter (the dataset's only filter).
_SKIP_ZSTD = 1
#: What a sink holds unwritten at most (a chunk being written, the pending bytes): what
#: closing it on a full disk writes, uncompressed at worst.
MAX_UNWRITTEN_BYTES = 2 * WORDS_CHUNK
_COL = {name: i for i, name in enumerate(EVT_INDEX_COLUMNS)}


def state_size(fmt: str) -> int:
    """Length of a `fmt` decoder's state array (the index columns after `EVT_INDEX_COLUMNS`)."""
    return int(StreamDecoder(fmt).state_copy().shape[0])


@dataclass(slots=True)
class _Row:
    """The index row being built: chunks that continue each other, merged."""

    start: int
    length: int
    events: int
    t_first: int
    t_last: int
    shift: int
    state: NDArray[np.int64]
    last: EvtChunk
    follows: bool

    def as_array(self) -> NDArray[np.int64]:
        head = [
            self.start,
            self.length,
            self.events,
            self.t_first,
            self.t_last,
            self.shift,
            int(self.follows),
        ]
        return np.concatenate([np.asarray(head, np.int64), self.state.astype(np.int64)])


@dataclass(slots=True)
class EvtWordsSink(TriggerIn):
    """One event sensor stored as EVT words: `/events/<name>` and its trigger-in group."""

    name: str
    group: h5py.Group
    width: int
    height: int
    fmt: str
    words: h5py.Dataset
    index: h5py.Dataset
    trig: dict[str, h5py.Dataset]
    n_bytes: int = 0
    """Bytes stored (written or buffered)."""
    n_words_written: int = 0
    """Bytes in whole chunks of evt_words (a multiple of WORDS_CHUNK while recording)."""
    alloc: int = 0
    """evt_words' extent (runs ahead of the data)."""
    pend: bytearray = field(default_factory=bytearray)
    """Bytes past the last whole chunk written."""
    row: _Row | None = None
    rows: list[NDArray[np.int64]] = field(default_factory=list)
    """Closed rows not written yet."""
    n_rows_written: int = 0
    n_written: int = 0
    """Events stored (rows written or buffered): what finalize and the notes count."""
    first_t: int | None = None
    last_t: int | None = None
    trig_parts: list[TriggerEvents] = field(default_factory=list)
    trig_host_parts: list[NDArray[np.int64]] = field(default_factory=list)
    n_trig_buffered: int = 0
    n_trig_written: int = 0
    tail: h5py.Dataset | None = None
    tail_meta: NDArray[np.int64] = field(default_factory=lambda: np.zeros((2, 2), np.int64))
    tail_slot: int = 0
    appendable: bool = True
    refused: int = 0
    """Batches refused whole (their bytes not stored)."""
    prev: EvtChunk | None = None
    """The last chunk stored (None after a refused one): whether the next row `follows`."""
    stats: DeviceWriteStats = field(default_factory=lambda: DeviceWriteStats("event_sensor"))
    compress: bool = True
    """False while the writer is behind: whole chunks are stored as they are (HDF5's filter mask
    says so per chunk, and readers skip the decompression for them), trading bytes on disk for
    writer time instead of shedding events."""
    write_failed: bool = False
    """A chunk write failed (disk full): every later one is checked to be in HDF5's index."""
    _zstd: Any = field(default_factory=lambda: zstandard.ZstdCompressor(level=_ZSTD_LEVEL))

    @classmethod
    def create(cls, name: str, g: h5py.Group, width: int, height: int, fmt: str) -> Self:
        """Lay out a new sensor's datasets in its (already created) group."""
        g.attrs[Device.WIDTH], g.attrs[Device.HEIGHT] = int(width), int(height)
        g.attrs[Events.STORAGE] = Storage.EVT_WORDS
        g.attrs[Events.EVT_FORMAT] = fmt
        words = g.create_dataset(
            Events.EVT_WORDS,
            shape=(0,),
            maxshape=(None,),
            dtype=np.uint8,
            chunks=(WORDS_CHUNK,),
            **hdf5plugin.Zstd(clevel=_ZSTD_LEVEL),
        )
        ncol = len(EVT_INDEX_COLUMNS) + state_size(fmt)
        index = g.create_dataset(
            Events.EVT_INDEX,
            shape=(0, ncol),
            maxshape=(None, ncol),
            dtype=np.int64,
            chunks=(_INDEX_CHUNK, ncol),
        )
        index.attrs[Events.EVT_INDEX_COLUMNS_ATTR] = ",".join(
            [*EVT_INDEX_COLUMNS, *(f"state{i}" for i in range(ncol - len(EVT_INDEX_COLUMNS)))]
        )
        g.create_dataset(Events.T_OFFSET, data=np.int64(0))  # finalize sets it, as for columns
        tg = g.create_group(Events.TRIGGER)
        trig = {k: new_series(tg, k, dt, {}) for k, dt in TRIGGER_DTYPES.items()}
        return cls(name, g, int(width), int(height), fmt, words, index, trig)

    @classmethod
    def reopen(cls, name: str, g: h5py.Group, where: str) -> Self:
        """The sink of a resumed take, from what `check_repair` left consistent."""
        words = require_dataset(g, Events.EVT_WORDS, where)
        index = require_dataset(g, Events.EVT_INDEX, where)
        tg = require_group(g, Events.TRIGGER, where)
        trig = {k: require_dataset(tg, k, where) for k in TRIGGER_DTYPES}
        missing = [k for k in (Device.WIDTH, Device.HEIGHT, Events.EVT_FORMAT) if k not in g.attrs]
        if missing:
            raise TakeFormatError(f"{where}: {g.name}: missing attribute(s) {missing}")
        rows = np.asarray(index[...], dtype=np.int64)
        fmt = g.attrs[Events.EVT_FORMAT]
        sink = cls(
            name,
            g,
            int(g.attrs[Device.WIDTH]),
            int(g.attrs[Device.HEIGHT]),
            fmt.decode() if isinstance(fmt, bytes) else str(fmt),
            words,
            index,
            trig,
            appendable=False,
            n_trig_written=int(trig[TriggerEdges.T].shape[0]),
        )
        sink.n_rows_written = int(rows.shape[0])
        if rows.shape[0]:
            sink.n_bytes = sink.n_words_written = int(rows[-1, 0] + rows[-1, 1])
            sink.n_written = int(rows[:, _COL["events"]].sum())
            sink.first_t, sink.last_t = int(rows[0, _COL["t_first"]]), int(rows[-1, _COL["t_last"]])
        sink.alloc = int(words.shape[0])
        sink.stats.items = sink.n_written
        return sink

    def datasets(self) -> list[h5py.Dataset]:
        return [self.words, self.index, *self.trig.values()]

    # -- appends -----------------------------------------------------------------------
    def add_packet(self, packet: EventPacket, path: Path) -> None:
        """Store a packet's words, its decoded events checked whole first (a refused batch
        leaves no byte behind, and the next one starts a new row from its own state)."""
        raw = packet.raw
        where = f"{path}: /{EVENTS_GROUP}/{self.name}"
        span = packet.span
        if raw is None and not span.n:
            return  # trigger edges alone (a window gate kept them, not the packet's words)
        if raw is None:
            raise TakeError(f"{where}: stores EVT words, but a packet came without them")
        if raw.fmt != self.fmt:
            raise TakeError(f"{where}: stores {self.fmt} words, but a packet carries {raw.fmt}")
        n = span.n
        if n:
            try:
                if self.last_t is not None and span.t_first < self.last_t:
                    raise TakeError(
                        f"{where}: event 0 of the batch (#{self.n_written} of the sensor) has "
                        f"t={span.t_first} us before the previous event at {self.last_t} us; "
                        f"batch of {n} refused"
                    )
                if raw.geometry != (self.width, self.height):
                    # the decoder that made the events had another geometry: check them (the
                    # order inside was the production decoder's to keep)
                    check_event_batch(
                        packet.events, where, None, self.n_written, self.width, self.height, within=False
                    )
            except TakeError:
                self.refused += 1
                self._close_row()
                self.prev = None
                raise
        self._add_row(raw, span, int(raw.shift_us))
        self.prev = raw
        # Counted before the words go out: once in `pend` and the row, the packet is the
        # sink's, and a chunk write that fails (disk full) is retried by `fail` / `close`.
        if n:
            if self.first_t is None:
                self.first_t = span.t_first
            self.last_t = span.t_last
        self.n_written += n
        self.stats.items += n
        self.stats.raw_bytes += len(raw.data)
        try:
            self._append_words(raw.data)
        except OSError as exc:  # the words are in `pend`: `fail` / `close` write them
            raise WriteDeferredError(exc.errno or errno.EIO, exc.strerror or str(exc)) from exc

    def _add_row(self, raw: EvtChunk, span: EventSpan, shift: int) -> None:
        row = self.row
        n = span.n
        t0 = span.t_first if n else (self.last_t if self.last_t is not None else 0)
        t1 = span.t_last if n else t0
        if (
            row is not None
            and raw.continues(row.last)
            and row.shift == shift
            and row.length < ROW_BYTES
            and row.t_last - row.t_first < ROW_US
        ):
            row.length += len(raw.data)
            row.events += n
            if n:
                if not row.events - n:
                    row.t_first = t0
                row.t_last = t1
            row.last = raw
            return
        self._close_row()
        prev = self.prev
        follows = prev is not None and raw.continues(prev) and prev.shift_us == shift
        state = np.asarray(raw.state, np.int64)
        self.row = _Row(self.n_bytes, len(raw.data), n, t0, t1, shift, state, raw, follows)

    def _close_row(self) -> None:
        if self.row is not None and self.row.length:
            self.rows.append(self.row.as_array())
        self.row = None

    def _append_words(self, data: bytes) -> None:
        self.pend += data
        self.n_bytes += len(data)
        if len(self.pend) >= WORDS_CHUNK:
            self._write_whole_chunks()

    def _write_whole_chunks(self) -> None:
        # Each chunk goes out as its own bytes, never as a view of `pend`: a write that fails
        # (disk full) keeps its arguments alive in the traceback the capture holds on to, and
        # a view would then forbid every later resize of `pend` (BufferError), the one in
        # `fail` included, which left the take "recording" instead of "failed". What was
        # written leaves `pend` even when a later chunk fails, so a retry (`fail`, `close`)
        # starts where the file ends.
        whole = len(self.pend) // WORDS_CHUNK * WORDS_CHUNK
        done = 0
        view = memoryview(self.pend)
        try:
            while done < whole:
                self._write_chunk(bytes(view[done : done + WORDS_CHUNK]), self.n_words_written)
                self.n_words_written += WORDS_CHUNK
                done += WORDS_CHUNK
        finally:
            view.release()
            if done:
                self.pend = self.pend[done:]

    def _write_chunk(self, data: bytes, offset: int) -> None:
        """One whole chunk (the last one zero-padded): compressed here (Zstd releases the GIL),
        or stored as it is while the writer is behind. The padded last chunk is compressed
        always: trimming evt_words to the bytes stored makes HDF5 read that edge chunk through
        its filter, which fails on a chunk stored without it (the take would not close)."""
        if offset + WORDS_CHUNK > self.alloc:
            self.alloc = offset + _GROW_CHUNKS * WORDS_CHUNK
            self.words.resize((self.alloc,))
        compress = self.compress or len(data) < WORDS_CHUNK
        if len(data) < WORDS_CHUNK:
            data = bytes(data) + bytes(WORDS_CHUNK - len(data))
        try:
            if compress:
                write_chunk(self.words, (offset,), self._zstd.compress(data))
            else:
                write_chunk(self.words, (offset,), data, _SKIP_ZSTD)
        except Exception:
            self.write_failed = True
            raise
        if not compress:
            self.stats.uncompressed_chunks += 1
        if self.write_failed and not chunk_is_stored(self.words, (offset,)):
            raise TakeError(
                f"{self.words.file.filename}: {self.words.name}: the chunk at byte {offset}, written "
                "again after a failed write, is missing from HDF5's chunk index"
            )

    # -- flush and close ---------------------------------------------------------------
    def write(self, *, final: bool) -> None:
        """Write the closed rows and whole chunks; `final` (close, fail, finalize) also the
        partial last chunk, and trims evt_words to the bytes stored. Otherwise the partial
        chunk goes to a tail slot (a flush) and the row being built is closed."""
        self._close_row()
        if len(self.pend) >= WORDS_CHUNK:  # whole chunks a write that failed left pending
            self._write_whole_chunks()
        if final and self.pend:
            self._write_chunk(bytes(self.pend), self.n_words_written)
            self.n_words_written += len(self.pend)
            self.pend = bytearray()
        elif not final:
            self._write_tail()
        if self.rows:
            append_rows(self.index, self.n_rows_written, np.stack(self.rows))
            self.n_rows_written += len(self.rows)
            self.rows = []
        if final and self.alloc != self.n_words_written and self.appendable:
            self.words.resize((self.n_words_written,))
            self.alloc = self.n_words_written
            self.appendable = False

    def _write_tail(self) -> None:
        n = len(self.pend)
        if n == 0:
            return
        meta = self.tail_meta
        slot = choose_tail_slot(meta, self.tail_slot, self.n_words_written)
        if self.tail is None:
            self.tail = self.group.create_dataset(
                Events.TAIL_WORDS, shape=(2, WORDS_CHUNK), dtype=np.uint8, fillvalue=0
            )
        have = int(meta[slot, 1])
        self.tail[slot, have:n] = np.frombuffer(self.pend, np.uint8)[have:n]
        meta[slot, 1] = n
        self.tail_slot = slot
        self.group.attrs.modify(Events.TAIL_WORDS_META, meta)  # in place: no attribute heap churn

    def drop_tails(self) -> None:
        """After everything is in evt_words (close, fail, finalize) the tail slots go."""
        drop_words_tail(self.group)
        self.tail = None
        self.tail_meta[:] = 0

    # -- the EventStore interface (rigd.take.event_store) -------------------------------
    def append_packet(self, packet: EventPacket, path: Path) -> None:
        """Store a packet's words and its trigger edges; a chunk write that fails after the
        packet was taken (WriteDeferredError) still keeps its edges: the packet is the take's."""
        try:
            self.add_packet(packet, path)
        except WriteDeferredError:
            self.add_triggers(packet.triggers, packet.host_time_ns)
            raise
        self.add_triggers(packet.triggers, packet.host_time_ns)

    def add_events(self, events: EventArray, path: Path) -> None:
        raise TakeError(f"{path}: event sensor {self.name!r} stores EVT words: use append_packet")

    def write_buffers(self, *, final: bool) -> None:
        self.write(final=final)
        self.write_triggers()

    def set_compress(self, on: bool) -> None:
        self.compress = on

    def first_time(self) -> int | None:
        return self.first_t

    def events_in_take(self) -> int:
        """Once finalized, those inside the take window (a packet across its edge is stored
        whole and clipped on read); before, every stored one."""
        inside = self.group.attrs.get(Events.EVENTS_IN_WINDOW)
        return self.n_written if inside is None else int(inside)

    def finalize_times(self, finalizer: Finalizer, cmap: ClockMap, t_offset: int) -> None:
        finalizer.finalize_words(self, cmap, t_offset)


def drop_words_tail(g: h5py.Group) -> None:
    if Events.TAIL_WORDS in g:
        del g[Events.TAIL_WORDS]
    if Events.TAIL_WORDS_META in g.attrs:
        del g.attrs[Events.TAIL_WORDS_META]


def words_tail(g: h5py.Group, main_len: int) -> NDArray[np.uint8]:
    """The flushed tail bytes that continue evt_words at `main_len` (empty when none)."""
    ds = g.get(Events.TAIL_WORDS)
    if not isinstance(ds, h5py.Dataset) or Events.TAIL_WORDS_META not in g.attrs:
        return np.empty(0, np.uint8)
    meta = np.asarray(g.attrs[Events.TAIL_WORDS_META], dtype=np.int64).reshape(-1, 2)
    best = np.empty(0, np.uint8)
    for slot, (start, n) in enumerate(meta):
        n = min(int(n), int(ds.shape[1]))
        if int(start) == main_len and n > best.shape[0]:
            best = np.asarray(ds[slot, :n], dtype=np.uint8)
    return best
