# mypy: disable-error-code="arg-type,assignment,call-arg,return-value"
"""EVT 3.0 (16-bit stateful words) decoder kernel and streaming encoder, OpenEB semantics.

Time is t = loop << 24 | TIME_HIGH << 12 | TIME_LOW; `loop` increments when TIME_HIGH falls by
>= 2048 (the 24-bit counter rolled over); a smaller fall is a jump back in time when the
TIME_HIGH values after it confirm it (see `kernels.JUMP_CONFIRM`): the decoder then shifts every
later time so the new base follows the old one and records the jump; otherwise it is a
non-monotonic violation and the word is skipped (tolerant), so time never runs backwards.
TIME_HIGH resets TIME_LOW to 0, like OpenEB's decoder. A TIME_LOW below the previous one under
the same TIME_HIGH is passed through as OpenEB does (the real Gen4.1 sample contains such words).
Words before the first TIME_HIGH are skipped (the stream was joined mid-way).

The kernels run in numba with all decoder state in a small int64 array so that a stream may be
cut anywhere between words; byte chunks cut mid-word are re-assembled by the caller.
"""

from __future__ import annotations

import logging

import numpy as np
from numba import njit
from numpy.typing import NDArray

from rigd.core.events import EventArray, TriggerEvents
from rigd.evt.encoder import StreamEncoder
from rigd.evt.errors import (
    BEFORE_TIME_HIGH,
    EVENT_WITHOUT_Y,
    HOLD,
    JUMP_COUNT,
    MAX_JUMP_RECORDS,
    NON_MONOTONIC_TIME,
    NON_MONOTONIC_TIME_HIGH,
    OK,
    OUT_OF_RANGE_XY,
    TIME_HIGH_JUMP,
    UNKNOWN_TYPE,
    VECTOR_WITHOUT_BASE,
)
from rigd.evt.kernels import (
    I8,
    I64,
    JUMP_ACCEPT,
    JUMP_LOOKAHEAD,
    JUMP_REJECT,
    JUMP_UNDECIDED,
    TRIG_T,
    U8,
    U16,
    DecodeConfig,
    DecodeOut,
    T,
    X,
    accept_jump,
    ctpop,
    keep_last_times,
    last_time,
    put_checked,
    put_run,
    put_trigger,
    skipped,
    violation,
)

log = logging.getLogger(__name__)

WORD_BYTES = 2
MAX_EVENTS_PER_WORD = 12
# what the decoder's outputs are first sized for: sensors' streams stay below one event a word
# (0.71 on the Gen4.1 recording, whose vectors are sparse); denser ones grow them
OUTPUT_EVENTS_PER_WORD = 1

# decoder state slots: loop, TIME_HIGH and TIME_LOW are the stream's own clock; ST_SHIFT (a
# multiple of 4096 us) is added to every time from the last accepted jump back on; the last two
# are the times of the last event and trigger edge emitted (before this call's outputs), so that
# no later one is emitted earlier
_ST_STARTED, _ST_LOOP, _ST_TH, _ST_TL, _ST_Y, _ST_BASE, _ST_VPOL, ST_SHIFT, ST_TEV, ST_TTR = range(10)
STATE_SIZE = 10


def new_decoder_state() -> NDArray[np.int64]:
    """Fresh decoder state: no time base, no y, no vector base, nothing emitted."""
    st = np.zeros(STATE_SIZE, np.int64)
    st[_ST_Y] = -1
    st[_ST_BASE] = -1
    st[ST_TEV] = -1
    st[ST_TTR] = -1
    return st


def stream_time(st: NDArray[np.int64]) -> int | None:
    """The stream's current time (us) after what was decoded, time words included; None
    before the first TIME_HIGH. A sensor's periodic TIME_HIGH words move it on with no events."""
    if not st[_ST_STARTED]:
        return None
    return ((int(st[_ST_LOOP]) << 24) | (int(st[_ST_TH]) << 12) | int(st[_ST_TL])) + int(st[ST_SHIFT])


NOBASE = 1 << 40  # vector base while none was given (any vector then fails the x check)


@njit(inline="always")
def load_state(st: I64) -> tuple[int, int, int, int, int, int, int, int]:  # pragma: no cover - numba
    """(started, loop, TIME_HIGH, y, vector base or NOBASE, vector polarity, shift, time) of a
    decoder state: what the kernels keep in registers."""
    loop = st[1]
    th = st[2]
    shift = st[ST_SHIFT]
    base = st[5] if st[5] >= 0 else NOBASE
    return st[0], loop, th, st[4], base, st[6], shift, ((loop << 24) | (th << 12) | st[3]) + shift


@njit(inline="always")
def store_state(  # pragma: no cover - numba
    st: I64, started: int, loop: int, th: int, tcur: int, y: int, base: int, vpol: int
) -> None:
    """The registers back into the state (the shift is the caller's to set)."""
    st[0] = started
    st[1] = loop
    st[2] = th
    st[3] = tcur & 0xFFF
    st[4] = y
    st[5] = base if base < NOBASE else -1
    st[6] = vpol


_NOY = 0xFFFF  # y while none was given (>= any height, so events fail the y check)
_BIG = 1 << 50
_FAST_TYPES = (0x0, 0x2, 0x3, 0x4, 0x5, 0x6)


def _type_row(t: int) -> list[int]:
    """Per-type constants of the fast loop: [is-ADDR_X mask, highest x offset for the range check
    (+BIG: slow type, -BIG: emits nothing), vector bits, ADDR_Y mask, TIME_LOW bits,
    VECT_BASE_X mask, vector step, pad]."""
    hi = {0x4: 11, 0x5: 7, 0x2: 0}.get(t, -_BIG if t in _FAST_TYPES else _BIG)
    return [
        -1 if t == 0x2 else 0,
        hi,
        {0x4: 0xFFF, 0x5: 0xFF}.get(t, 0),
        -1 if t == 0x0 else 0,
        0xFFF if t == 0x6 else 0,
        -1 if t == 0x3 else 0,
        {0x4: 12, 0x5: 8}.get(t, 0),
        0,
    ]


_TAB = np.array([_type_row(t) for t in range(16)], np.int64)
_U64 = np.uint64  # unsigned indices: no negative-index wrap-around code in the loop


# TIME_HIGH steps larger than this (cameras step by 1) are checked by `_refuted`; smaller jumps
# are taken as they come (a corrupt *next* word could otherwise refute a valid one).
TH_JUMP = 16


@njit(inline="always")
def _refuted(buf: U16, pos: int, th: int, v12: int) -> bool:  # pragma: no cover - numba
    """Whether the TIME_HIGH v12 at `pos`, a jump (or roll-over) from th, is a corrupt word: the
    next TIME_HIGH in the buffer is a shorter step (mod 4096) from th than its distance (either
    way) from v12. A valid jump is never refuted: the next one is v12 + d, and with jump + d < 4096
    (steps <= 2047, as the encoder and cameras make) it is farther from th; nor is one followed by
    a corrupt word just below it. With no next TIME_HIGH in the buffer the
    jump is taken, as OpenEB does."""
    q = pos + 1
    while q < buf.shape[0]:
        w = np.int64(buf[_U64(q)])
        if (w >> 12) == 0x8:
            v2 = w & 0xFFF
            ahead = (v2 - v12) & 0xFFF
            return ((v2 - th) & 0xFFF) < min(ahead, 4096 - ahead)
        q += 1
    return False


@njit(inline="always")
def _jump_verdict(  # pragma: no cover - numba
    buf: U16, pos: int, th: int, v12: int, cfg: DecodeConfig
) -> tuple[int, int]:
    """Whether the TIME_HIGH v12 at `pos`, a small fall from th, starts a jump back in time: the
    next TIME_HIGH values (repeats aside) rise from it and stay below th until cfg's confirm count
    of values was seen (accept), or one falls or reaches th (reject: the old base goes on, so the
    word was corrupt). Undecided when the buffer ends first, unless it is the stream's last
    (cfg final) or JUMP_LOOKAHEAD words were looked at (reject). Also returns the events in the
    words before the deciding one (exact for valid words): what acceptance keeps."""
    need = cfg[4] - 1
    prev = v12
    held = 0
    q = pos + 1
    stop = min(buf.shape[0], pos + 1 + JUMP_LOOKAHEAD)
    while q < stop:
        w = np.int64(buf[_U64(q)])
        typ = w >> 12
        if typ == 0x8:
            v = w & 0xFFF
            if v != prev:
                if v < prev or v >= th:
                    return JUMP_REJECT, held
                need -= 1
                if need <= 0:
                    return JUMP_ACCEPT, held
                prev = v
        elif typ == 0x2:
            held += 1
        elif typ == 0x4 or typ == 0x5:
            held += ctpop(w & (0xFFF if typ == 0x4 else 0xFF))
        q += 1
    if cfg[3] or q >= pos + 1 + JUMP_LOOKAHEAD:
        return JUMP_REJECT, held
    return JUMP_UNDECIDED, held


# This reference kernel and `evt3_fast.decode_kernel` are kept as two kernels on purpose: each is
# the other's oracle (tests compare them word by word), the fast one falls back to this one for
# every irregular word, and each loop's shape is what makes it fast or exact (see evt3_fast's
# measurements); the stores and checks they share live in `kernels`.
@njit(nogil=True, cache=True)
def decode_kernel(
    buf: U16, pos: int, end: int, st: I64, out: DecodeOut, n: int, nt: int, stats: I64, cfg: DecodeConfig
) -> tuple[int, int, int, int]:
    """Decode words buf[pos:end] (word indices) into `out` from event n and trigger nt on; stop
    early when outputs are nearly full or on a strict-mode violation (then pos is the offending
    word). Returns (pos, n, nt, error code); `st` carries the format state to the next call.

    The inner loop handles the words that make up ~all of a valid stream (ADDR_Y, ADDR_X,
    VECT_BASE_X, VECT_12, VECT_8, TIME_LOW) without a data-dependent branch: per-type masks come
    from `_TAB`, every word stores one (possibly dummy) event at n and advances n by whether it
    emitted, and state updates are masked merges. One sign test routes a word to the slow path
    when it could violate the format (no TIME_HIGH yet, no/out-of-range y, x beyond the width,
    vector without base) or is a rare type; the slow path is the reference per-word semantics.

    Time never runs backwards in the output: a falling TIME_LOW goes to the slow path, and while
    the time is below the last emitted event's (a corrupt TIME_LOW/TIME_HIGH, a stray word) every
    word takes the slow path, which drops the events and triggers that would go back in time as
    non_monotonic_time (strict mode stops there) until the time base is back at or past them.
    """
    width = cfg[0]
    height = cfg[1]
    strict = cfg[2]
    cap = out[X].shape[0] - 12
    tcap = out[TRIG_T].shape[0]
    started, loop, th, y, base, vpol, shift, tcur = load_state(st)
    wm1 = width - 1
    err = OK
    while pos < end:
        # fast loop: words that cannot violate the format (checked by one sign test)
        yk = y if y >= 0 else _NOY
        hlim = height - 1 if started and tcur >= last_time(out[T], n, st[ST_TEV]) else -1
        while pos < end:
            if n > cap:
                break
            w = np.int64(buf[_U64(pos)])
            typ = w >> 12
            v = w & 0x7FF
            mx = _TAB[typ, 0]
            mtl = _TAB[typ, 4]
            ebase = (base & ~mx) | (v & mx)
            # (a falling TIME_LOW makes the last term negative)
            if ((hlim - yk) | (wm1 - (ebase + _TAB[typ, 1])) | ((w & mtl) - (tcur & mtl))) < 0:
                break
            polv = ((w >> 10) & 2) - 1
            # ADDR_X (mx = -1): one event at v; a vector (mx = 0): its mask's pixels from base
            emask = (w & _TAB[typ, 2]) | (mx & 1)
            n = put_run(out, n, ebase, emask, yk, (vpol & ~mx) | (polv & mx), tcur)
            my = _TAB[typ, 3]
            mb = _TAB[typ, 5]
            yk = (yk & ~my) | (v & my)
            tcur = (tcur & ~mtl) | (w & mtl)
            vpol = (vpol & ~mb) | (polv & mb)
            base = (base & ~mb) + ((v & mb) + _TAB[typ, 6])
            pos += 1
        y = -1 if yk == _NOY else yk
        if pos >= end or n > cap:
            break
        # ---- slow path: one word, original semantics for every type
        w = np.int64(buf[_U64(pos)])
        typ = w >> 12
        v = w & 0x7FF
        if typ == 0x2 or typ == 0x4 or typ == 0x5:  # ADDR_X, VECT_12, VECT_8
            vector = typ != 0x2
            if vector and base >= NOBASE:
                err = violation(stats, VECTOR_WITHOUT_BASE, strict, pos)
                if err:
                    break
            elif started == 0:
                stats[BEFORE_TIME_HIGH] += 1
            elif y < 0:
                err = violation(stats, EVENT_WITHOUT_Y, strict, pos)
                if err:
                    break
            else:
                if vector:
                    x0, mask, pol = base, w & (0xFFF if typ == 0x4 else 0xFF), vpol
                else:
                    x0, mask, pol = v, 1, 1 if (w & 0x800) != 0 else -1
                if tcur < last_time(out[T], n, st[ST_TEV]):  # would go back in time: dropped
                    if strict:
                        stats[NON_MONOTONIC_TIME] += 1
                        err = NON_MONOTONIC_TIME
                        break
                    if mask != 0:
                        skipped(stats, NON_MONOTONIC_TIME, ctpop(mask), pos)
                else:
                    n, bad = put_checked(out, n, x0, mask, y, pol, tcur, stats, cfg, pos)
                    if bad and strict:
                        err = OUT_OF_RANGE_XY
                        break
            if vector and base < NOBASE:
                base += 12 if typ == 0x4 else 8
        elif typ == 0x0:
            y = v
        elif typ == 0x6:
            tcur = (tcur & ~0xFFF) | (w & 0xFFF)
        elif typ == 0x3:
            base = v
            vpol = 1 if (w & 0x800) != 0 else -1
        # TIME_HIGH handling is written out here and in evt2's kernel on purpose: the formats'
        # bit widths differ, and the control flow (break, hold) stays in the hot loop.
        elif typ == 0x8:
            v12 = w & 0xFFF
            fell = started != 0 and v12 < th
            if fell and th - v12 < 2048:  # a small fall: a jump back in time, or a corrupt word
                verdict, held = _jump_verdict(buf, pos, th, v12, cfg)
                if verdict == JUMP_UNDECIDED:
                    err = HOLD  # the decoder comes back here with more words
                    break
                if verdict == JUMP_REJECT:
                    err = violation(stats, NON_MONOTONIC_TIME_HIGH, strict, pos)
                    if err:
                        break
                else:
                    if stats[JUMP_COUNT] >= MAX_JUMP_RECORDS:
                        break  # the decoder takes the records and comes back here
                    shift = accept_jump(stats, pos, loop << 24, th, v12, 12, shift, held)
                    th = v12
                    tcur = ((loop << 24) | (th << 12)) + shift
            elif (
                started != 0 and (v12 - th) + (4096 if fell else 0) > TH_JUMP and _refuted(buf, pos, th, v12)
            ):
                err = violation(stats, TIME_HIGH_JUMP, strict, pos)
                if err:
                    break
            else:
                if fell:  # a large fall: the 24-bit counter rolled over
                    loop += 1
                started = 1
                th = v12
                tcur = ((loop << 24) | (th << 12)) + shift
        elif typ == 0xA:
            if started == 0:
                stats[BEFORE_TIME_HIGH] += 1
            elif tcur < last_time(out[TRIG_T], nt, st[ST_TTR]):  # would go back in time: dropped
                err = violation(stats, NON_MONOTONIC_TIME, strict, pos)
                if err:
                    break
            else:
                if nt >= tcap:
                    break
                nt = put_trigger(out, nt, tcur, w & 1, (w >> 8) & 0xF)
        elif typ == 0x7 or typ == 0xE or typ == 0xF:
            pass
        else:
            err = violation(stats, UNKNOWN_TYPE, strict, pos)
            if err:
                break
        pos += 1
    store_state(st, started, loop, th, tcur, y, base, vpol)
    st[ST_SHIFT] = shift
    keep_last_times(st, out, n, nt)
    return pos, n, nt, err


# encoder state: [started, full TIME_HIGH (with loops), last TIME_LOW or -1, last y or -1]
_TH_STEP = 2047  # largest TIME_HIGH step that a decoder can never mistake for a roll-over


@njit(nogil=True, cache=True)
def encode_kernel(
    x: U16, y: U16, p: I8, t: I64, tt: I64, tp: U8, tc: U8, st: I64, out: U16, write: bool
) -> int:
    """Encode time-sorted events and triggers; returns the word count (write=False only counts)."""
    ne = t.shape[0]
    ntr = tt.shape[0]
    i = 0
    j = 0
    k = 0
    while i < ne or j < ntr:
        trigger = j < ntr and (i >= ne or tt[j] <= t[i])  # a trigger goes first on a tie
        tv = tt[j] if trigger else t[i]
        # TIME_HIGH words up to tv (the stream's first even at 0), stepped by at most _TH_STEP,
        # then TIME_LOW when it changed
        thf = tv >> 12
        while st[0] == 0 or st[1] < thf:
            st[0] = 1
            st[1] += min(thf - st[1], _TH_STEP)
            st[2] = -1
            if write:
                out[k] = 0x8000 | (st[1] & 0xFFF)
            k += 1
        if st[2] != tv & 0xFFF:
            st[2] = tv & 0xFFF
            if write:
                out[k] = 0x6000 | st[2]
            k += 1
        if trigger:
            if write:
                out[k] = 0xA000 | ((np.int64(tc[j]) & 0xF) << 8) | (np.int64(tp[j]) & 1)
            k += 1
            j += 1
            continue
        yy = np.int64(y[i])
        pp = p[i]
        e = i + 1
        while e < ne and t[e] == tv and y[e] == y[i] and p[e] == pp and x[e] > x[e - 1]:
            e += 1
        if st[3] != yy:
            st[3] = yy
            if write:
                out[k] = yy
            k += 1
        pol = 0x800 if pp > 0 else 0
        if e - i < 3:
            for q in range(i, e):
                if write:
                    out[k] = 0x2000 | pol | np.int64(x[q])
                k += 1
        else:
            q = i
            need_base = True
            base = 0
            while q < e:
                if need_base:
                    base = np.int64(x[q])
                    if write:
                        out[k] = 0x3000 | pol | base
                    k += 1
                    need_base = False
                mask = 0
                m = q
                while m < e and np.int64(x[m]) < base + 12:
                    mask |= 1 << (np.int64(x[m]) - base)
                    m += 1
                vector, step = (0x5000, 8) if m >= e and mask < 256 else (0x4000, 12)
                if write:
                    out[k] = vector | mask
                k += 1
                base += step
                q = m
                if q < e and np.int64(x[q]) >= base + 12:
                    need_base = True
        i = e
    return k


class Evt3Encoder(StreamEncoder):
    """Streaming EVT 3.0 encoder: successive `encode` calls continue one byte stream.

    Same-time, same-row, same-polarity runs of increasing x (what a sensor readout produces)
    become VECT_BASE_X + VECT_12/VECT_8 words; isolated events become EVT_ADDR_X. TIME_HIGH is
    stepped by at most 2047 units so a decoder always recognises roll-overs; the stream starts
    with time base 0, as a freshly reset camera does.
    """

    def __init__(self) -> None:
        super().__init__(encode_kernel, np.array([0, 0, -1, -1], np.int64), np.uint16, max_channel=0xF)

    def mark_time(self, t_us: int) -> bytes:
        """TIME_HIGH / TIME_LOW words that move the stream's time to `t_us` with no event, as a
        sensor's periodic time words do: the reader learns the stream has got that far. A mark
        before what was already encoded moves nothing."""
        t = max(int(t_us), self._last_t)
        st, words = self._state, []
        thf = t >> 12
        while st[0] == 0 or st[1] < thf:
            st[0] = 1
            st[1] += min(thf - int(st[1]), _TH_STEP)
            st[2] = -1
            words.append(0x8000 | (int(st[1]) & 0xFFF))
        if st[2] != t & 0xFFF:
            st[2] = t & 0xFFF
            words.append(0x6000 | int(st[2]))
        self._last_t = t
        return np.asarray(words, "<u2").tobytes()


def encode_evt3(events: EventArray, triggers: TriggerEvents | None = None) -> bytes:
    """One-shot EVT 3.0 encoding of a whole recording."""
    return Evt3Encoder().encode(events, triggers)
