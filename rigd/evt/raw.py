"""Prophesee RAW byte streams and files: the streaming decoder, header parsing and writing.

`StreamDecoder` is the one decoding path for files, replayed streams and live cameras: it accepts
byte chunks cut anywhere (mid-word, mid-vector, across TIME_HIGH), carries the partial word and
the format state between calls, and runs the numba kernels over whole words. Its memory is one
output batch per call, so files of any size decode in constant memory through `RawReader`.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from rigd.core.errors import EventDataError
from rigd.core.events import EventArray, EventPacket, EventSpan, EvtChunk, TriggerEvents
from rigd.evt import evt2, evt3, evt3_fast, evt21
from rigd.evt.errors import (
    HOLD,
    JUMP_COUNT,
    KIND_NAMES,
    MAX_SKIP_OFFSETS,
    SKIP_COUNT,
    SKIP_POS,
    STATS_SIZE,
    TRUNCATED,
    EvtDecodeError,
)
from rigd.evt.evt3_scan import scan_kernel
from rigd.evt.jumps import MAX_KEPT_JUMPS, TimeJump, jump_counters, take_jumps
from rigd.evt.kernels import JUMP_CONFIRM, DecodeConfig, DecodeKernel, decode_config, decode_out

log = logging.getLogger(__name__)

EvtFormat = Literal["evt2", "evt21", "evt21_le", "evt3"]
FORMATS: tuple[str, ...] = ("evt2", "evt21", "evt21_le", "evt3")
# EVT 3.0 kernel: branchy clean-stretch loop with the reference state machine as fallback
# (evt3_fast); False selects the reference `evt3.decode_kernel` alone (tests, benchmarks)
USE_EVT3_FAST = True
# ids of decoded byte streams (EvtChunk.stream): unique per decoder within the process
_STREAM_IDS = itertools.count(1)


@dataclass(frozen=True, slots=True)
class Decoded:
    """Events and trigger edges decoded from one piece of a stream."""

    events: EventArray
    triggers: TriggerEvents

    @staticmethod
    def empty() -> Decoded:
        return Decoded(EventArray.empty(), TriggerEvents.empty())

    @staticmethod
    def concatenate(parts: list[Decoded]) -> Decoded:
        return Decoded(
            EventArray.concatenate([d.events for d in parts]),
            TriggerEvents.concatenate([d.triggers for d in parts]),
        )


@dataclass(frozen=True, slots=True)
class Scanned:
    """What `StreamDecoder.scan_chunk` tells of a piece of the stream: its events' span and its
    trigger edges, and its events when the piece had to be decoded (None: only scanned)."""

    span: EventSpan
    triggers: TriggerEvents
    events: EventArray | None

    @classmethod
    def of(cls, decoded: Decoded) -> Scanned:
        return cls(EventSpan.of(decoded.events), decoded.triggers, decoded.events)

    @property
    def empty(self) -> bool:
        return not self.span.n and not len(self.triggers)

    def packet(self, host_time_ns: int, raw: EvtChunk | None) -> EventPacket:
        """The event packet of these words (`raw`), decoded later where they were only scanned."""
        if self.events is not None:
            return EventPacket(self.events, self.triggers, host_time_ns, raw)
        if raw is None:
            raise EventDataError("a scanned packet needs its words")
        return EventPacket.scanned(self.span, self.triggers, host_time_ns, raw, decode_chunk)


#: Trigger edges a scan stores per call before it hands the piece to the decoder instead.
_SCAN_TRIGGERS = 64


class _Out:
    """Growable output arrays handed to the kernels; grown (never per event) when nearly full and
    cut to their events (`_cut`) when done."""

    def __init__(self, n_events: int, n_triggers: int) -> None:
        self.arrays = decode_out(n_events, n_triggers)
        self.n = 0
        self.nt = 0

    def grow(self, min_free: int, ahead: int = 0) -> None:
        """Room for at least `min_free` more events and one more trigger edge; `ahead`: the events
        the rest of the input is expected to hold, so that one copy usually does."""
        (x, y, p, t, tt, tp, tc), n, nt = self.arrays, self.n, self.nt
        if x.shape[0] - n <= min_free:
            size = max(2 * x.shape[0], n + ahead + 2 * min_free + 1024)
            x, y, p, t = (_grown(a, size, n) for a in (x, y, p, t))
        if tt.shape[0] - nt <= 0:
            size = 2 * tt.shape[0] + 64
            tt, tp, tc = (_grown(a, size, nt) for a in (tt, tp, tc))
        self.arrays = (x, y, p, t, tt, tp, tc)

    def result(self, compact: bool = False) -> Decoded:
        """The outputs' filled part; `compact`: a sparse result gives its reserve back (`_cut`)."""
        (x, y, p, t, tt, tp, tc), n, nt = self.arrays, self.n, self.nt
        return Decoded(
            EventArray(*(_cut(a, n, compact) for a in (x, y, p, t))),
            TriggerEvents(*(_cut(a, nt, compact) for a in (tt, tp, tc))),
        )


def _grown(old: NDArray[Any], size: int, keep: int) -> NDArray[Any]:
    """A larger copy of old holding its first `keep` items."""
    new = np.empty(size, old.dtype)
    new[:keep] = old[:keep]
    return new


def _cut(a: NDArray[Any], n: int, compact: bool) -> NDArray[Any]:
    """`a`'s first n items. EVT 3.0 outputs (`compact`) are sized for more than a stream usually
    holds: at least half used (a sensor's stream: 0.71 of one event a word on the Gen4.1
    recording), the slice keeps the whole array, whose unused tail a fresh allocation never
    touched; less used (a sparse stream), the events are copied out so the reserve goes back.
    Shrinking in place (numpy's resize, a realloc) was measured and rejected: glibc then sizes its
    next map by the shrunk block, so every chunk of a reader whose caller keeps the previous one
    faulted in fresh pages (+40 % of a streaming decode)."""
    if n == a.shape[0] or not compact or 2 * n >= a.shape[0]:
        return a[:n]
    return a[:n].copy()


class StreamDecoder:
    """Incremental decoder of one EVT byte stream.

    strict=False skips what violates the format, counts it in `stats` by kind and goes on;
    strict=True raises `EvtDecodeError` naming the absolute byte offset (`offset` = where the
    stream starts in its file, e.g. the RAW header size) and the violation. After an error the
    decoder must not be fed again. Events outside width x height are violations too (a header
    that lies about geometry must not produce impossible pixels), and so is an event or trigger
    edge earlier than the last one emitted: output time never runs backwards, so a corrupt word
    costs the events it corrupts and not a take (whose writer refuses out-of-order batches).
    `skipped_offsets` holds the absolute byte offsets of the first few skipped items.

    A TIME_HIGH that falls a little is a jump back in time (not a corrupt word) when the next
    `jump_confirm` - 1 new TIME_HIGH values go on rising from it below the old one: every later
    time is then shifted so the new base follows the old one, and the jump is recorded in
    `time_jumps` (the first few in full in `jumps`). Until the bytes tell, the words from that
    TIME_HIGH on are held back (kept for the next `feed`; `finish` or `flush` decides with what
    there is), so the result never depends on where the chunks were cut.

    `feed_chunk` / `flush_chunk` also return the bytes a call decoded as an `EvtChunk` with the
    kernel state before them (`state_copy`), so a take can store the words as sent and a reader
    decode any stored piece on its own with `StreamDecoder(fmt, state=...)`: a kernel that holds
    words back leaves its state at the start of what it holds, so each chunk starts where the
    previous one ended.
    """

    def __init__(
        self,
        fmt: str,
        *,
        width: int = 1280,
        height: int = 720,
        strict: bool = False,
        offset: int = 0,
        jump_confirm: int = JUMP_CONFIRM,
        state: NDArray[np.int64] | None = None,
    ) -> None:
        if fmt not in FORMATS:
            raise EventDataError(f"unknown EVT format {fmt!r}; expected one of {FORMATS}")
        if not (0 < width <= 2048 and 0 < height <= 2048):
            raise EventDataError(f"sensor geometry {width}x{height} outside 1..2048")
        if not 2 <= jump_confirm <= 64:
            raise EventDataError(
                f"jump_confirm {jump_confirm} outside 2..64 (TIME_HIGH values that confirm a jump back; "
                "1 would take a single corrupt word for one)"
            )
        self.fmt = fmt
        self.width = int(width)
        self.height = int(height)
        self.strict = bool(strict)
        mod: Any = {"evt2": evt2, "evt3": evt3, "evt21": evt21, "evt21_le": evt21}[fmt]
        self._word = int(mod.WORD_BYTES)
        self._max_per_word = int(mod.MAX_EVENTS_PER_WORD)
        self._state = mod.new_decoder_state()
        if state is not None:
            given = np.asarray(state)
            if given.shape != self._state.shape or given.dtype.kind not in "iu":
                raise EventDataError(
                    f"{fmt} decoder state must be {self._state.shape[0]} integers, "
                    f"got shape {given.shape} {given.dtype}"
                )
            self._state[:] = given
        self._mod = mod
        self.stream = next(_STREAM_IDS)
        # kernels read native words; EVT 2.1 words are read as two u32 halves (layout-dependent)
        self._dtype = np.dtype({2: "<u2", 4: "<u4", 8: "<u4"}[self._word])
        self._step = 2 if self._word == 8 else 1
        kernels: dict[str, DecodeKernel] = {
            "evt2": evt2.decode_kernel,
            "evt21": evt21.decode_kernel,
            "evt21_le": evt21.decode_kernel_le,
            "evt3": evt3_fast.decode_kernel if USE_EVT3_FAST else evt3.decode_kernel,
        }
        self._kernel = kernels[fmt]
        self.jump_confirm = int(jump_confirm)
        self._cfg = decode_config(self.width, self.height, self.strict, confirm=self.jump_confirm)
        self._final_cfg = decode_config(
            self.width, self.height, self.strict, final=True, confirm=self.jump_confirm
        )
        # events a word the outputs are first sized for (EVT 2.0: one; EVT 2.1 vectors: up to 32,
        # sized by bytes; EVT 3.0: its module's guess, and a sparse result is compacted)
        self._guess = int(getattr(mod, "OUTPUT_EVENTS_PER_WORD", min(self._max_per_word, self._word)))
        self._compact = hasattr(mod, "OUTPUT_EVENTS_PER_WORD")
        self._stats = np.zeros(STATS_SIZE, np.int64)
        self.skipped_offsets: list[int] = []
        self.jumps: list[TimeJump] = []
        self.time_jumps = 0
        self._jump_held = 0
        self._pending = b""  # bytes not decoded yet: a partial word, or words held at a time jump
        self._base = int(offset)
        self.bytes_consumed = 0

    @property
    def time_us(self) -> int | None:
        """How far the stream has got (us, time words included); None where the format's
        decoder does not say (only EVT 3.0 does) or before its first time word."""
        fn = getattr(self._mod, "stream_time", None)
        return None if fn is None else fn(self._state)

    @property
    def stats(self) -> dict[str, int]:
        """Skipped items by kind (events for pixel-level kinds, words otherwise)."""
        return {name: int(self._stats[code]) for code, name in KIND_NAMES.items()}

    @property
    def jump_stats(self) -> dict[str, int]:
        """Counters of the accepted time jumps (`jumps.jump_counters`); empty when none."""
        return jump_counters(self.jumps, self.time_jumps, self._jump_held)

    def state_copy(self) -> NDArray[np.int64]:
        """The kernel state now: where the next byte not yet decoded (`pending` included) starts."""
        return self._state.copy()

    @property
    def pending(self) -> bytes:
        """Bytes kept for the next call: a partial word, or the words held at a time jump."""
        return self._pending

    @property
    def holding(self) -> bool:
        """Whether words are held back at a TIME_HIGH not yet told a jump or a corrupt word."""
        return len(self._pending) >= self._word

    def _words(self, raw: NDArray[np.uint8]) -> tuple[NDArray[np.uint8], NDArray[Any]]:
        """Whole words' bytes and their view as the kernel's words."""
        if raw.ctypes.data % self._word:
            raw = raw.copy()  # chunk cut mid-word left the body unaligned; one memcpy
        return raw, raw.view(self._dtype)

    def _run(
        self, raw: NDArray[np.uint8], buf: NDArray[Any], out: _Out, abs_start: int, cfg: DecodeConfig
    ) -> int:
        """Decode the words; returns how many: fewer than all when the kernel holds the rest back."""
        pos, end = 0, buf.shape[0] // self._step
        ws = self._word
        while pos < end:
            seen = int(self._stats[SKIP_COUNT])
            pos, out.n, out.nt, err = self._kernel(
                buf, pos, end, self._state, out.arrays, out.n, out.nt, self._stats, cfg
            )
            if self._stats[SKIP_COUNT] > seen:  # word positions of this call's first skips
                self.skipped_offsets += [
                    abs_start + int(w) * ws
                    for w in self._stats[SKIP_POS + seen : SKIP_POS + self._stats[SKIP_COUNT]]
                ]
                self._stats[SKIP_COUNT] = len(self.skipped_offsets)
            if self._stats[JUMP_COUNT]:
                self._took(take_jumps(self._stats, abs_start, ws))
            if err == HOLD:
                return pos
            if err:
                word = bytes(raw[pos * ws : (pos + 1) * ws])[::-1].hex()
                off = abs_start + pos * ws
                kind = KIND_NAMES[err]
                self.bytes_consumed = off - self._base
                raise EvtDecodeError(
                    f"{self.fmt}: {kind} at byte offset {off} (word 0x{word})", offset=off, kind=kind
                )
            if pos < end:  # outputs full: room for the rest at the density so far, and a quarter
                rate = min(self._max_per_word, 5 * out.n // max(4 * pos, 1) + 1)
                out.grow(self._max_per_word, ahead=(end - pos) * rate)
        return end

    def _took(self, jumps: list[TimeJump]) -> None:
        for jump in jumps:
            self.time_jumps += 1
            self._jump_held += jump.held_events
            if len(self.jumps) < MAX_KEPT_JUMPS:
                self.jumps.append(jump)
                log.warning("%s", jump.line(self.fmt))

    def feed(self, data: bytes | bytearray | memoryview | NDArray[np.uint8]) -> Decoded:
        """Decode the next chunk; a trailing partial word, and the words from a TIME_HIGH that
        the bytes so far do not tell a jump or a corrupt word, are kept for the next call."""
        arr = np.frombuffer(data, np.uint8) if len(data) else np.empty(0, np.uint8)
        if self.holding:  # rare: one copy to decode the held words on with the new ones
            arr = np.concatenate([np.frombuffer(self._pending, np.uint8), arr])
            self._pending = b""
        return self._decode(arr, self._cfg)

    def feed_chunk(self, data: bytes | bytearray | memoryview) -> tuple[Decoded, EvtChunk]:
        """`feed`, and the bytes it decoded (pending ones before `data` included, those it
        keeps pending now excluded) with the state before them: decoding the chunk's data from
        its state gives exactly what this call returned."""
        state, before, offset = self._state.copy(), self._pending, self.bytes_consumed
        decoded = self.feed(data)
        return decoded, self._chunk(state, before, data, offset)

    def scan(self, data: bytes) -> Scanned:
        """`feed` for a capture that stores the words: the events are counted, not decoded,
        where the words are those of a valid stream (EVT 3.0); anything else (held or partial
        words, a word the scan does not mirror) is decoded by `feed`, whose events then come
        along. Either way the decoder's state afterwards is the same."""
        if self.fmt != "evt3" or self._pending or not data or len(data) % self._word:
            return Scanned.of(self.feed(data))
        _, words = self._words(np.frombuffer(data, np.uint8))
        st = self._state.copy()
        trig = (
            np.empty(_SCAN_TRIGGERS, np.int64),
            np.empty(_SCAN_TRIGGERS, np.uint8),
            np.empty(_SCAN_TRIGGERS, np.uint8),
        )
        clean, n, t_first, t_last, nt = scan_kernel(words, st, self.width, self.height, *trig)
        if not clean:
            return Scanned.of(self.feed(data))
        self._state[:] = st
        self.bytes_consumed += len(data)
        span = EventSpan(int(n), int(t_first), int(t_last)) if n else EventSpan(0, -1, -1)
        return Scanned(span, TriggerEvents(trig[0][:nt], trig[1][:nt], trig[2][:nt]), None)

    def scan_chunk(self, data: bytes) -> tuple[Scanned, EvtChunk]:
        """`scan`, and the bytes it took as a chunk, as `feed_chunk` does."""
        state, before, offset = self._state.copy(), self._pending, self.bytes_consumed
        scanned = self.scan(data)
        return scanned, self._chunk(state, before, data, offset)

    def flush_chunk(self) -> tuple[Decoded, EvtChunk | None]:
        """`flush`, and its words as a chunk (None when nothing was held)."""
        if not self.holding:
            return Decoded.empty(), None
        state, before, offset = self._state.copy(), self._pending, self.bytes_consumed
        decoded = self.flush()
        return decoded, self._chunk(state, before, b"", offset)

    def _chunk(
        self, state: NDArray[np.int64], before: bytes, data: bytes | bytearray | memoryview, offset: int
    ) -> EvtChunk:
        used = self.bytes_consumed - offset
        if used <= len(before):
            body = before[:used]
        elif not before:
            body = bytes(data[:used])
        else:
            body = before + bytes(data[: used - len(before)])
        if len(before) + len(data) - len(self._pending) != used:  # the contract, checked: cheap
            raise EventDataError(
                f"{self.fmt}: decoder accounting: {used} bytes consumed, {len(before)} + {len(data)} "
                f"given and {len(self._pending)} pending"
            )
        return EvtChunk(self.fmt, body, state, self.stream, offset, geometry=(self.width, self.height))

    def _decode(self, arr: NDArray[np.uint8], cfg: DecodeConfig) -> Decoded:
        """Decode what is pending (at most a partial word) and then arr."""
        ws = self._word
        total = len(self._pending) + arr.shape[0]
        nwords = total // ws
        if nwords == 0:
            self._pending += arr.tobytes()
            return Decoded.empty()
        start = self._base + self.bytes_consumed
        head = None
        if self._pending:
            need = ws - len(self._pending)
            head = np.frombuffer(self._pending + arr[:need].tobytes(), np.uint8)
            arr = arr[need:]
        whole = (arr.shape[0] // ws) * ws
        body, words = self._words(arr[:whole])
        # outputs for one event a word: a sensor's EVT 3.0 stream stays below it (0.71 on the
        # Gen4.1 recording), so a counting pass over the words (a tenth of the decode) is not
        # worth its exact size; denser vectors grow the outputs once (`_run`)
        cap_events = nwords * self._guess + 2 * self._max_per_word + 1
        out = _Out(cap_events, 16 + nwords // 64)
        done = 0
        if head is not None:
            if not self._run(*self._words(head), out, start, cfg):
                # a TIME_HIGH to judge with the words after it: decode it with them (rare: a copy)
                self._pending = b""
                return self._decode(np.concatenate([head, arr]), cfg)
            self.bytes_consumed += ws
            start += ws
        if whole:
            done = self._run(body, words, out, start, cfg)
        self._pending = arr[done * ws :].tobytes()
        self.bytes_consumed += done * ws
        return out.result(self._compact)

    def flush(self) -> Decoded:
        """Decide held words now, with no more bytes to come (a live stream that stopped): a
        jump still unconfirmed is taken for a corrupt word, as at the end of a stream."""
        if not self.holding:
            return Decoded.empty()
        held = np.frombuffer(self._pending, np.uint8)
        self._pending = b""
        return self._decode(held, self._final_cfg)

    def finish(self) -> Decoded:
        """End of stream: held words are decided (`flush`), and a leftover partial word is a
        truncation (raised or counted). Returns what the held words decode to."""
        out = self.flush()
        if self._pending:
            off = self._base + self.bytes_consumed
            n = len(self._pending)
            self._pending = b""
            if self.strict:
                raise EvtDecodeError(
                    f"{self.fmt}: truncated: stream ends with {n} byte(s) of a {self._word}-byte word "
                    f"at byte offset {off}",
                    offset=off,
                    kind=KIND_NAMES[TRUNCATED],
                )
            self._stats[TRUNCATED] += 1
            if len(self.skipped_offsets) < MAX_SKIP_OFFSETS:
                self.skipped_offsets.append(off)
                self._stats[SKIP_COUNT] = len(self.skipped_offsets)
            log.warning("%s stream ends with %d byte(s) of a partial word at offset %d", self.fmt, n, off)
        return out

    def log_stats(self) -> None:
        """Report skipped items and accepted time jumps once, so tolerant decoding is never silent."""
        skipped = {k: v for k, v in self.stats.items() if v}
        if skipped:
            log.warning(
                "%s decode skipped items: %s (first at byte offsets %s)",
                self.fmt,
                skipped,
                self.skipped_offsets,
            )
        if self.time_jumps:
            log.warning(
                "%s stream time jumped back %d time(s), first at byte offsets %s; later times shifted",
                self.fmt,
                self.time_jumps,
                [j.offset for j in self.jumps],
            )


def decode_from_state(
    fmt: str, data: bytes | NDArray[np.uint8], state: NDArray[np.int64], width: int, height: int
) -> EventArray:
    """The events of a stored or sent piece of a stream, decoded on their own from the decoder
    state before it (the words a kernel would hold back at its end decided with what is there)."""
    dec = StreamDecoder(fmt, width=width, height=height, state=state)
    events = dec.feed(data).events
    held = dec.flush().events
    return EventArray.concatenate([events, held]) if len(held) else events


def decode_chunk(chunk: EvtChunk) -> EventArray:
    """A chunk's events decoded on their own from its state, with its shift added: what a
    packet that was only scanned (`EventPacket.scanned`) holds."""
    if chunk.geometry is None:
        raise EventDataError(
            f"{chunk.fmt} chunk at byte {chunk.offset} of stream {chunk.stream}: no geometry to decode with"
        )
    events = decode_from_state(chunk.fmt, chunk.data, chunk.state, *chunk.geometry)
    return events.with_time(events.t + chunk.shift_us) if chunk.shift_us else events


def decode_bytes(
    data: bytes | bytearray | memoryview,
    fmt: str,
    *,
    width: int = 1280,
    height: int = 720,
    strict: bool = False,
    jump_confirm: int = JUMP_CONFIRM,
) -> Decoded:
    """Decode a complete in-memory stream (no header)."""
    dec = StreamDecoder(fmt, width=width, height=height, strict=strict, jump_confirm=jump_confirm)
    out = join_decoded(dec.feed(data), dec.finish())
    dec.log_stats()
    return out


def join_decoded(a: Decoded, b: Decoded) -> Decoded:
    """a then b, without a copy when b is empty (the usual end of a stream)."""
    return a if not len(b.events) and not len(b.triggers) else Decoded.concatenate([a, b])
