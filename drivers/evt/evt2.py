# mypy: disable-error-code="arg-type,assignment"
"""EVT 2.0 (32-bit little-endian words) decoder kernel and streaming encoder, OpenEB semantics.

t = TIME_HIGH << 6 | ts, a 34-bit time base that rolls over every 2^34 us (~4.77 h): a TIME_HIGH
that falls by >= 2^27 is a roll-over (loop += 2^34), a smaller fall a non-monotonic violation
whose word is skipped. Words before the first TIME_HIGH are skipped, as OpenEB does.

EVT 2.1 (evt21.py) is EVT 2.0 with a 32-pixel validity mask beside each word, so the decode
kernels of both formats come from the factory here. The layout is a closure constant that numba compiles
away: the EVT 2.0 kernels keep no mask loop and no half-word reads.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

from drivers.evt.errors import BEFORE_TIME_HIGH, NON_MONOTONIC_TIME_HIGH, OK, OUT_OF_RANGE_XY, UNKNOWN_TYPE
from drivers.evt.evt3 import _check_inputs
from drivers.evt.kernels import (
    I64,
    U32,
    DecodeConfig,
    DecodeKernel,
    DecodeOut,
    put_checked,
    put_trigger,
)
from rigd.core.errors import EventDataError
from rigd.core.events import EventArray, TriggerEvents

WORD_BYTES = 4
MAX_EVENTS_PER_WORD = 1
STATE_SIZE = 3  # started, loop, time_high

TH_HALF = 1 << 27
TH_STEP = TH_HALF - 1


def new_decoder_state() -> NDArray[np.int64]:
    return np.zeros(STATE_SIZE, np.int64)


def make_decode_kernel(masked: bool, swapped: bool = False) -> DecodeKernel:
    """EVT 2.0 decode kernel, or with `masked` EVT 2.1's (u32 pairs: the word and its validity mask;
    `swapped`: the word's half comes first, IMX636's layout)."""
    per_word = 32 if masked else 1
    hi = 0 if swapped else 1  # index of the word's half in a masked word's u32 pair

    @njit(nogil=True, cache=True)
    def decode_kernel(
        buf: U32, pos: int, end: int, st: I64, out: DecodeOut, n: int, nt: int, stats: I64, cfg: DecodeConfig
    ) -> tuple[int, int, int, int]:
        """Decode whole words buf[pos:end] (word indices); the contract of `evt3.decode_kernel`."""
        cap = out.x.shape[0] - per_word
        tcap = out.tt.shape[0]
        started = st[0]
        loop = st[1]
        th = st[2]
        tbase = (loop << 34) | (th << 6)
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
                    n, bad = put_checked(out, n, (w >> 11) & 0x7FF, mask, w & 0x7FF, pol, t, stats, cfg)
                    if bad and cfg.strict:
                        err = OUT_OF_RANGE_XY
                        break
            elif typ == 0x8:  # EVT_TIME_HIGH
                v = w & 0xFFFFFFF
                fell = started != 0 and v < th
                if fell and th - v < TH_HALF:  # a small fall: the word is skipped
                    stats[NON_MONOTONIC_TIME_HIGH] += 1
                    if cfg.strict:
                        err = NON_MONOTONIC_TIME_HIGH
                        break
                else:
                    if fell:  # a large fall: the counter rolled over
                        loop += 1
                    started = 1
                    th = v
                    tbase = (loop << 34) | (th << 6)
            elif typ == 0xA:  # EXT_TRIGGER
                if started == 0:
                    stats[BEFORE_TIME_HIGH] += 1
                else:
                    nt = put_trigger(out, nt, tbase | ((w >> 22) & 0x3F), w & 1, (w >> 8) & 0x1F)
            elif typ == 0xE or typ == 0xF:  # OTHERS / CONTINUED
                pass
            else:
                stats[UNKNOWN_TYPE] += 1
                if cfg.strict:
                    err = UNKNOWN_TYPE
                    break
            pos += 1
        st[0] = started
        st[1] = loop
        st[2] = th
        return pos, n, nt, err

    return decode_kernel


decode_kernel = make_decode_kernel(masked=False)


@njit(nogil=True, cache=True)
def _emit_time(out: NDArray[np.uint32], k: int, st: NDArray[np.int64], tv: int, write: bool) -> int:
    thf = tv >> 6
    if st[0] == 0:
        first = min(thf, TH_STEP)
        if write:
            out[k] = (0x8 << 28) | first
        k += 1
        st[0] = 1
        st[1] = first
    while st[1] < thf:
        st[1] += min(thf - st[1], TH_STEP)
        if write:
            out[k] = (0x8 << 28) | (st[1] & 0xFFFFFFF)
        k += 1
    return k


@njit(nogil=True, cache=True)
def encode_kernel(
    x: NDArray[np.uint16],
    y: NDArray[np.uint16],
    p: NDArray[np.int8],
    t: NDArray[np.int64],
    tt: NDArray[np.int64],
    tp: NDArray[np.uint8],
    tc: NDArray[np.uint8],
    st: NDArray[np.int64],
    out: NDArray[np.uint32],
    write: bool,
) -> int:
    """Encode time-sorted events and triggers (one word each); write=False only counts."""
    ne = t.shape[0]
    ntr = tt.shape[0]
    i = 0
    j = 0
    k = 0
    while i < ne or j < ntr:
        if j < ntr and (i >= ne or tt[j] <= t[i]):
            k = _emit_time(out, k, st, tt[j], write)
            if write:
                out[k] = (
                    (0xA << 28)
                    | ((tt[j] & 0x3F) << 22)
                    | ((np.int64(tc[j]) & 0x1F) << 8)
                    | (np.int64(tp[j]) & 1)
                )
            k += 1
            j += 1
        else:
            k = _emit_time(out, k, st, t[i], write)
            if write:
                typ = 1 if p[i] > 0 else 0
                out[k] = (typ << 28) | ((t[i] & 0x3F) << 22) | (np.int64(x[i]) << 11) | np.int64(y[i])
            k += 1
            i += 1
    return k


class Evt2Encoder:
    """Streaming EVT 2.0 encoder; the stream starts at time base 0 like a reset camera."""

    def __init__(self) -> None:
        self._state = np.zeros(2, np.int64)
        self._last_t = 0

    def encode(self, events: EventArray, triggers: TriggerEvents | None = None) -> bytes:
        trig = triggers if triggers is not None else TriggerEvents.empty()
        _check_inputs(events, trig, self._last_t, 0x1F)
        if len(events) and int(events.t[0]) < 0:
            raise EventDataError("negative event time cannot be encoded")
        args = (events.x, events.y, events.p, events.t, trig.t, trig.p, trig.channel)
        nwords = encode_kernel(*args, self._state.copy(), np.empty(0, np.uint32), False)
        out = np.empty(nwords, np.uint32)
        encode_kernel(*args, self._state, out, True)
        for arr in (events.t, trig.t):
            if arr.size:
                self._last_t = max(self._last_t, int(arr[-1]))
        return out.astype("<u4", copy=False).tobytes()


def encode_evt2(events: EventArray, triggers: TriggerEvents | None = None) -> bytes:
    """One-shot EVT 2.0 encoding of a whole recording."""
    return Evt2Encoder().encode(events, triggers)
