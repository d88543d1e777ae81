# mypy: disable-error-code="arg-type,assignment,call-arg,return-value"
"""EVT 2.0 (32-bit little-endian words) decoder kernel and streaming encoder, OpenEB semantics.

t = TIME_HIGH << 6 | ts, a 34-bit time base that rolls over every 2^34 us (~4.77 h): a TIME_HIGH
that falls by >= 2^27 is a roll-over (loop += 2^34); a smaller fall is a jump back in time when
the TIME_HIGH values after it confirm it (`kernels.JUMP_CONFIRM`; later times are shifted so the
new base follows the old one, and the jump is recorded), else a non-monotonic violation whose word
is skipped. Words before the first TIME_HIGH are skipped, as OpenEB does. An event or
trigger edge earlier than the last one emitted (a corrupt ts or TIME_HIGH) is dropped and counted
as non_monotonic_time, so the output time never runs backwards. A TIME_HIGH jump (a step over 16,
or a roll-over) that the next TIME_HIGH in the buffer contradicts is skipped as time_high_jump.

EVT 2.1 (evt21.py) is EVT 2.0 with a 32-pixel validity mask beside each word, so the kernels of
both formats come from the factories here. The layout is a closure constant that numba compiles
away: the EVT 2.0 kernels keep no mask loop and no half-word reads.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

from rigd.core.events import EventArray, TriggerEvents
from rigd.evt.encoder import EncodeKernel, StreamEncoder
from rigd.evt.errors import (
    BEFORE_TIME_HIGH,
    HOLD,
    JUMP_COUNT,
    MAX_JUMP_RECORDS,
    NON_MONOTONIC_TIME,
    NON_MONOTONIC_TIME_HIGH,
    OK,
    OUT_OF_RANGE_XY,
    TIME_HIGH_JUMP,
    UNKNOWN_TYPE,
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
    U32,
    DecodeConfig,
    DecodeKernel,
    DecodeOut,
    T,
    X,
    accept_jump,
    ctpop,
    keep_last_times,
    last_time,
    put_checked,
    put_trigger,
    skipped,
    violation,
)

WORD_BYTES = 4
MAX_EVENTS_PER_WORD = 1
# started, loop, time_high (the stream's clock), the shift added to every time from the last
# accepted jump back on (whole 64 us periods), last event time, last trigger time
STATE_SIZE = 6

TH_HALF = 1 << 27
TH_STEP = TH_HALF - 1
_TH_NEAR = 16  # larger TIME_HIGH jumps (cameras step by 1) are checked against the next one
_TIME_HIGH = 0x8 << 28
_EXT_TRIGGER = 0xA << 28


def new_decoder_state() -> NDArray[np.int64]:
    """Fresh state: no time base, nothing emitted."""
    return np.array([0, 0, 0, 0, -1, -1], np.int64)


def make_decode_kernel(masked: bool, swapped: bool = False) -> DecodeKernel:
    """EVT 2.0 decode kernel, or with `masked` EVT 2.1's (u32 pairs: the word and its validity mask;
    `swapped`: the word's half comes first, IMX636's layout)."""
    per_word = 32 if masked else 1
    hi = 0 if swapped else 1  # index of the word's half in a masked word's u32 pair

    @njit(inline="always")
    def refuted(buf: U32, pos: int, th: int, v: int) -> bool:  # pragma: no cover - numba
        """Whether TIME_HIGH v at `pos`, a jump or roll-over from th, is a corrupt word: the next
        TIME_HIGH in the buffer continues th and not v (`evt3._refuted`'s rule, 28-bit counter)."""
        q = pos + 1
        nwords = buf.shape[0] // (2 if masked else 1)
        while q < nwords:
            wq = np.int64(buf[2 * q + hi]) if masked else np.int64(buf[q])
            if (wq >> 28) == 0x8:
                v2 = wq & 0xFFFFFFF
                ahead = (v2 - v) & 0xFFFFFFF
                return ((v2 - th) & 0xFFFFFFF) < min(ahead, (1 << 28) - ahead)
            q += 1
        return False

    @njit(inline="always")
    def jump_verdict(  # pragma: no cover - numba
        buf: U32, pos: int, th: int, v: int, cfg: DecodeConfig
    ) -> tuple[int, int]:
        """Whether TIME_HIGH v at `pos`, a small fall from th, starts a jump back in time, and the
        events before the deciding word (`evt3._jump_verdict`'s rule, 28-bit counter)."""
        need = cfg[4] - 1
        prev = v
        held = 0
        q = pos + 1
        stop = min(buf.shape[0] // (2 if masked else 1), pos + 1 + JUMP_LOOKAHEAD)
        while q < stop:
            wq = np.int64(buf[2 * q + hi]) if masked else np.int64(buf[q])
            tq = wq >> 28
            if tq == 0x8:
                vq = wq & 0xFFFFFFF
                if vq != prev:
                    if vq < prev or vq >= th:
                        return JUMP_REJECT, held
                    need -= 1
                    if need <= 0:
                        return JUMP_ACCEPT, held
                    prev = vq
            elif tq <= 1:
                held += ctpop(np.int64(buf[2 * q + 1 - hi])) if masked else 1
            q += 1
        if cfg[3] or q >= pos + 1 + JUMP_LOOKAHEAD:
            return JUMP_REJECT, held
        return JUMP_UNDECIDED, held

    @njit(nogil=True, cache=True)
    def decode_kernel(
        buf: U32, pos: int, end: int, st: I64, out: DecodeOut, n: int, nt: int, stats: I64, cfg: DecodeConfig
    ) -> tuple[int, int, int, int]:
        """Decode whole words buf[pos:end] (word indices); the contract of `evt3.decode_kernel`."""
        strict = cfg[2]
        cap = out[X].shape[0] - per_word
        tcap = out[TRIG_T].shape[0]
        started = st[0]
        loop = st[1]
        th = st[2]
        shift = st[3]
        tbase = ((loop << 34) | (th << 6)) + shift
        err = OK
        while pos < end:
            if n > cap or nt >= tcap:
                break
            if masked:
                w = np.int64(buf[2 * pos + hi])
                mask = np.int64(buf[2 * pos + 1 - hi])
            else:
                w = np.int64(buf[pos])
                mask = np.int64(1)
            typ = w >> 28
            if typ <= 1:  # CD_OFF / CD_ON (EVT 2.1: EVT_NEG / EVT_POS)
                if started == 0:
                    stats[BEFORE_TIME_HIGH] += 1
                else:
                    t = tbase | ((w >> 22) & 0x3F)
                    pol = 1 if typ == 1 else -1
                    if t < last_time(out[T], n, st[4]):  # would go back in time: dropped
                        if strict:
                            stats[NON_MONOTONIC_TIME] += 1
                            err = NON_MONOTONIC_TIME
                            break
                        if mask != 0:
                            skipped(stats, NON_MONOTONIC_TIME, ctpop(mask), pos)
                    else:
                        n, bad = put_checked(
                            out, n, (w >> 11) & 0x7FF, mask, w & 0x7FF, pol, t, stats, cfg, pos
                        )
                        if bad and strict:
                            err = OUT_OF_RANGE_XY
                            break
            # TIME_HIGH handling is written out here and in evt3.decode_kernel on purpose: the
            # formats' bit widths differ, and the control flow (break, hold) stays in the hot loop.
            elif typ == 0x8:  # EVT_TIME_HIGH
                v = w & 0xFFFFFFF
                fell = started != 0 and v < th
                if fell and th - v < TH_HALF:  # a small fall: a jump back in time, or a corrupt word
                    verdict, held = jump_verdict(buf, pos, th, v, cfg)
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
                        shift = accept_jump(stats, pos, loop << 34, th, v, 6, shift, held)
                        th = v
                        tbase = ((loop << 34) | (th << 6)) + shift
                elif (
                    started != 0
                    and (v - th) + (1 << 28 if fell else 0) > _TH_NEAR
                    and refuted(buf, pos, th, v)
                ):
                    err = violation(stats, TIME_HIGH_JUMP, strict, pos)
                    if err:
                        break
                else:
                    if fell:  # a large fall: the counter rolled over
                        loop += 1
                    started = 1
                    th = v
                    tbase = ((loop << 34) | (th << 6)) + shift
            elif typ == 0xA:  # EXT_TRIGGER
                if started == 0:
                    stats[BEFORE_TIME_HIGH] += 1
                else:
                    t = tbase | ((w >> 22) & 0x3F)
                    if t < last_time(out[TRIG_T], nt, st[5]):  # would go back in time: dropped
                        err = violation(stats, NON_MONOTONIC_TIME, strict, pos)
                        if err:
                            break
                    else:
                        nt = put_trigger(out, nt, t, w & 1, (w >> 8) & 0x1F)
            elif typ == 0xE or typ == 0xF:  # OTHERS / CONTINUED
                pass
            else:
                err = violation(stats, UNKNOWN_TYPE, strict, pos)
                if err:
                    break
            pos += 1
        st[0] = started
        st[1] = loop
        st[2] = th
        st[3] = shift
        keep_last_times(st, out, n, nt)
        return pos, n, nt, err

    return decode_kernel


def make_encode_kernel(masked: bool, swapped: bool = False) -> EncodeKernel:
    """EVT 2.0 encode kernel, or with `masked` EVT 2.1's, in `make_decode_kernel`'s layouts."""
    n_u32 = 2 if masked else 1  # u32s a word
    hi = 0 if swapped or not masked else 1  # where the word's type/time/x/y half goes among them

    @njit(nogil=True, cache=True)
    def encode_kernel(
        x: U16, y: U16, p: I8, t: I64, tt: I64, tp: U8, tc: U8, st: I64, out: U32, write: bool
    ) -> int:
        """Encode time-sorted events and triggers into u32s; returns their count (write=False only
        counts). EVT 2.1: same-t/y/p events of increasing x in one 32-pixel group share a word."""
        ne = t.shape[0]
        ntr = tt.shape[0]
        started = st[0]
        th = st[1]  # TIME_HIGH with its roll-overs
        i = 0
        j = 0
        k = 0
        while i < ne or j < ntr:
            trigger = j < ntr and (i >= ne or tt[j] <= t[i])  # a trigger goes first on a tie
            tv = tt[j] if trigger else t[i]
            # TIME_HIGH words up to tv (the stream's first even at 0), stepped so that a decoder
            # never takes a step for a roll-over
            thf = tv >> 6
            while started == 0 or th < thf:
                started = 1
                th += min(thf - th, TH_STEP)
                if write:
                    out[k + hi] = _TIME_HIGH | (th & 0xFFFFFFF)
                    if masked:
                        out[k + 1 - hi] = 0
                k += n_u32
            word = 0  # built only when writing: the counting pass needs the times alone
            mask = 0
            if trigger:
                if write:
                    word = _EXT_TRIGGER | ((tv & 0x3F) << 22) | ((np.int64(tc[j]) & 0x1F) << 8)
                    word |= np.int64(tp[j]) & 1
                j += 1
            else:
                e = i + 1
                if masked:
                    xb = np.int64(x[i]) & ~31
                    while (
                        e < ne
                        and t[e] == tv
                        and y[e] == y[i]
                        and p[e] == p[i]
                        and x[e] > x[e - 1]
                        and (np.int64(x[e]) & ~31) == xb
                    ):
                        e += 1
                if write:
                    xb = np.int64(x[i]) & ~31 if masked else np.int64(x[i])
                    if masked:
                        for q in range(i, e):
                            mask |= 1 << (np.int64(x[q]) - xb)
                    word = ((1 if p[i] > 0 else 0) << 28) | ((tv & 0x3F) << 22) | (xb << 11) | np.int64(y[i])
                i = e
            if write:
                out[k + hi] = word
                if masked:
                    out[k + 1 - hi] = mask
            k += n_u32
        st[0] = started
        st[1] = th
        return k

    return encode_kernel


decode_kernel = make_decode_kernel(masked=False)
encode_kernel = make_encode_kernel(masked=False)


class Evt2Encoder(StreamEncoder):
    """Streaming EVT 2.0 encoder."""

    def __init__(self) -> None:
        super().__init__(encode_kernel, np.zeros(2, np.int64), np.uint32, max_channel=0x1F)


def encode_evt2(events: EventArray, triggers: TriggerEvents | None = None) -> bytes:
    """One-shot EVT 2.0 encoding of a whole recording."""
    return Evt2Encoder().encode(events, triggers)
