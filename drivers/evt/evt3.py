# mypy: disable-error-code="arg-type,assignment,call-arg"
"""EVT 3.0 (16-bit stateful words) decoder kernel and streaming encoder, OpenEB semantics.

Time is t = loop << 24 | TIME_HIGH << 12 | TIME_LOW; `loop` increments when TIME_HIGH falls by
>= 2048 (the 24-bit counter rolled over); a smaller fall is a non-monotonic violation and the
word is skipped (tolerant) so time never runs backwards. TIME_HIGH resets TIME_LOW to 0, like
OpenEB's decoder. A TIME_LOW below the previous one under the same TIME_HIGH is passed through as
OpenEB does (the real Gen4.1 sample contains such words). Words before the first TIME_HIGH are
skipped (the stream was joined mid-way).

The kernels run in numba with all decoder state in a small int64 array so that a stream may be
cut anywhere between words; byte chunks cut mid-word are re-assembled by the caller.
"""

from __future__ import annotations

import logging

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic
from numpy.typing import NDArray

from drivers.evt.errors import (
    BEFORE_TIME_HIGH,
    EVENT_WITHOUT_Y,
    NON_MONOTONIC_TIME_HIGH,
    OUT_OF_RANGE_XY,
    UNKNOWN_TYPE,
    VECTOR_WITHOUT_BASE,
)
from rigd.core.errors import EventDataError
from rigd.core.events import EventArray, TriggerEvents

log = logging.getLogger(__name__)

WORD_BYTES = 2
MAX_EVENTS_PER_WORD = 12

# decoder state slots
_ST_STARTED, _ST_LOOP, _ST_TH, _ST_TL, _ST_Y, _ST_BASE, _ST_VPOL = range(7)
STATE_SIZE = 7


@intrinsic
def cttz(typingctx: object, x: types.Integer) -> object:
    """Count trailing zeros (one instruction): walks a validity mask's set bits without a
    data-dependent branch per bit."""
    sig = x(x)

    def codegen(context: object, builder: ir.IRBuilder, signature: object, args: list[ir.Value]) -> ir.Value:
        return builder.cttz(args[0], ir.Constant(ir.IntType(1), 0))

    return sig, codegen


def new_decoder_state() -> NDArray[np.int64]:
    """Fresh decoder state: no time base, no y, no vector base."""
    st = np.zeros(STATE_SIZE, np.int64)
    st[_ST_Y] = -1
    st[_ST_BASE] = -1
    return st


@njit(nogil=True, cache=True)
def decode_kernel(
    buf: NDArray[np.uint16],
    pos: int,
    end: int,
    st: NDArray[np.int64],
    ox: NDArray[np.uint16],
    oy: NDArray[np.uint16],
    op: NDArray[np.int8],
    ot: NDArray[np.int64],
    n: int,
    tt: NDArray[np.int64],
    tp: NDArray[np.uint8],
    tc: NDArray[np.uint8],
    nt: int,
    stats: NDArray[np.int64],
    width: int,
    height: int,
    strict: bool,
) -> tuple[int, int, int, int]:
    """Decode words buf[pos:end] (word indices); stop early when outputs are nearly full or on a
    strict-mode violation (then pos is the offending word). Returns (pos, n, nt, error_code)."""
    cap = ox.shape[0] - 12
    tcap = tt.shape[0]
    started = st[0]
    loop = st[1]
    th = st[2]
    tl = st[3]
    y = st[4]
    base = st[5]
    vpol = st[6]
    tbase = (loop << 24) | (th << 12)
    err = 0
    wm1 = width - 1
    hm1 = height - 1
    # hot counters live in registers, flushed to stats at the end (no store per word)
    c_oor = 0
    c_early = 0
    c_noy = 0
    while pos < end:
        if n > cap or nt >= tcap:
            break
        w = np.int64(buf[pos])
        typ = w >> 12
        if (0x4D >> typ) & 1:
            # ADDR_Y / ADDR_X / VECT_BASE_X / TIME_LOW: ~90% of real words. Handled without a
            # data-dependent branch (arithmetic selects): the type sequence is unpredictable, and
            # a mispredict per word would cost more than the few extra operations.
            v = w & 0x7FF
            is_y = np.int64(typ == 0x0)
            is_x = np.int64(typ == 0x2)
            is_b = np.int64(typ == 0x3)
            is_tl = np.int64(typ == 0x6)
            polv = ((w >> 10) & 2) - 1
            ox[n] = v
            oy[n] = y
            op[n] = polv
            ot[n] = tbase | tl
            ready = is_x & started & np.int64(y >= 0)
            inside = np.int64(v <= wm1) & np.int64(y <= hm1)
            n += ready & inside
            bad = ready & (1 - inside)
            c_oor += bad
            c_early += is_x & (1 - started)
            c_noy += is_x & started & np.int64(y < 0)
            y += (v - y) * is_y
            tl += ((w & 0xFFF) - tl) * is_tl
            base += (v - base) * is_b
            vpol += (polv - vpol) * is_b
            if strict and (bad | (is_x & started & np.int64(y < 0))):
                err = 3 if bad else 7
                break
            pos += 1
            continue
        if typ == 0x4 or typ == 0x5:  # VECT_12 / VECT_8
            if typ == 0x4:
                mask = w & 0xFFF
                step = 12
            else:
                mask = w & 0xFF
                step = 8
            if base < 0:
                stats[2] += 1
                if strict:
                    err = 2
                    break
            elif started == 0:
                stats[6] += 1
                base += step
            elif y < 0:
                stats[7] += 1
                if strict:
                    err = 7
                    break
                base += step
            else:
                if y >= height or base + step > width:
                    # slow path: check each set bit against the geometry
                    bad = False
                    m = mask
                    x = base
                    while m != 0:
                        if (m & 1) != 0:
                            if x >= width or y >= height:
                                stats[3] += 1
                                bad = True
                            else:
                                ox[n] = x
                                oy[n] = y
                                op[n] = vpol
                                ot[n] = tbase | tl
                                n += 1
                        m >>= 1
                        x += 1
                    if bad and strict:
                        err = 3
                        break
                else:
                    t = tbase | tl
                    m = mask
                    while m != 0:
                        ox[n] = base + cttz(m)
                        oy[n] = y
                        op[n] = vpol
                        ot[n] = t
                        n += 1
                        m &= m - 1
                base += step
        elif typ == 0x2:  # EVT_ADDR_X
            x = w & 0x7FF
            if started == 0:
                stats[6] += 1
            elif y < 0:
                stats[7] += 1
                if strict:
                    err = 7
                    break
            elif x >= width or y >= height:
                stats[3] += 1
                if strict:
                    err = 3
                    break
            else:
                ox[n] = x
                oy[n] = y
                op[n] = 1 if (w & 0x800) != 0 else -1
                ot[n] = tbase | tl
                n += 1
        elif typ == 0x0:  # EVT_ADDR_Y (bit 11: master/slave system type, ignored)
            y = w & 0x7FF
        elif typ == 0x6:  # EVT_TIME_LOW
            tl = w & 0xFFF
        elif typ == 0x3:  # VECT_BASE_X
            base = w & 0x7FF
            vpol = 1 if (w & 0x800) != 0 else -1
        elif typ == 0x8:  # EVT_TIME_HIGH
            v = w & 0xFFF
            if started != 0 and v < th:
                if th - v >= 2048:
                    loop += 1
                else:
                    stats[1] += 1
                    if strict:
                        err = 1
                        break
                    pos += 1
                    continue
            started = 1
            th = v
            tl = 0
            tbase = (loop << 24) | (th << 12)
        elif typ == 0xA:  # EXT_TRIGGER
            if started == 0:
                stats[6] += 1
            else:
                tt[nt] = tbase | tl
                tp[nt] = w & 1
                tc[nt] = (w >> 8) & 0xF
                nt += 1
        elif typ == 0x7 or typ == 0xE or typ == 0xF:  # CONTINUED_4 / OTHERS / CONTINUED_12
            pass
        else:
            stats[4] += 1
            if strict:
                err = 4
                break
        pos += 1
    stats[3] += c_oor
    stats[6] += c_early
    stats[7] += c_noy
    st[0] = started
    st[1] = loop
    st[2] = th
    st[3] = tl
    st[4] = y
    st[5] = base
    st[6] = vpol
    return pos, n, nt, err


# Keep the named codes referenced so readers can map the literal indices used in the kernel.
_KERNEL_CODES = (
    NON_MONOTONIC_TIME_HIGH,
    VECTOR_WITHOUT_BASE,
    OUT_OF_RANGE_XY,
    UNKNOWN_TYPE,
    BEFORE_TIME_HIGH,
    EVENT_WITHOUT_Y,
)
assert _KERNEL_CODES == (1, 2, 3, 4, 6, 7)

# encoder state: [started, full TIME_HIGH (with loops), last TIME_LOW or -1, last y or -1]
_TH_STEP = 2047  # largest TIME_HIGH step that a decoder can never mistake for a roll-over


@njit(nogil=True, cache=True)
def _emit(out: NDArray[np.uint16], k: int, word: int, write: bool) -> int:
    if write:
        out[k] = word
    return k + 1


@njit(nogil=True, cache=True)
def _emit_time(out: NDArray[np.uint16], k: int, st: NDArray[np.int64], tv: int, write: bool) -> int:
    thf = tv >> 12
    tl = tv & 0xFFF
    if st[0] == 0:
        first = min(thf, _TH_STEP)
        k = _emit(out, k, 0x8000 | first, write)
        st[0] = 1
        st[1] = first
        st[2] = -1
    while st[1] < thf:
        step = min(thf - st[1], _TH_STEP)
        st[1] += step
        k = _emit(out, k, 0x8000 | (st[1] & 0xFFF), write)
        st[2] = -1
    if st[2] != tl:
        k = _emit(out, k, 0x6000 | tl, write)
        st[2] = tl
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
    out: NDArray[np.uint16],
    write: bool,
) -> int:
    """Encode time-sorted events and triggers; with write=False only count the words."""
    ne = t.shape[0]
    ntr = tt.shape[0]
    i = 0
    j = 0
    k = 0
    while i < ne or j < ntr:
        if j < ntr and (i >= ne or tt[j] <= t[i]):
            k = _emit_time(out, k, st, tt[j], write)
            k = _emit(out, k, 0xA000 | ((np.int64(tc[j]) & 0xF) << 8) | (np.int64(tp[j]) & 1), write)
            j += 1
            continue
        tv = t[i]
        yy = np.int64(y[i])
        pp = p[i]
        e = i + 1
        while e < ne and t[e] == tv and y[e] == y[i] and p[e] == pp and x[e] > x[e - 1]:
            e += 1
        k = _emit_time(out, k, st, tv, write)
        if st[3] != yy:
            k = _emit(out, k, yy, write)
            st[3] = yy
        pol = 0x800 if pp > 0 else 0
        if e - i < 3:
            for q in range(i, e):
                k = _emit(out, k, 0x2000 | pol | np.int64(x[q]), write)
        else:
            q = i
            need_base = True
            base = 0
            while q < e:
                if need_base:
                    base = np.int64(x[q])
                    k = _emit(out, k, 0x3000 | pol | base, write)
                    need_base = False
                mask = 0
                m = q
                while m < e and np.int64(x[m]) < base + 12:
                    mask |= 1 << (np.int64(x[m]) - base)
                    m += 1
                if m >= e and mask < 256:
                    k = _emit(out, k, 0x5000 | mask, write)
                    base += 8
                else:
                    k = _emit(out, k, 0x4000 | mask, write)
                    base += 12
                q = m
                if q < e and np.int64(x[q]) >= base + 12:
                    need_base = True
        i = e
    return k


def _check_inputs(events: EventArray, triggers: TriggerEvents, last_t: int, max_channel: int) -> None:
    """Reject what the format cannot carry instead of emitting a stream that decodes differently."""
    for name, arr in (("events.t", events.t), ("triggers.t", triggers.t)):
        if arr.size:
            if arr[0] < last_t:
                raise EventDataError(f"{name} starts at {int(arr[0])} us, before the encoder's {last_t} us")
            if arr.size > 1 and (np.diff(arr) < 0).any():
                raise EventDataError(f"{name} is not sorted by time")
    if len(events) and (int(events.x.max()) > 2047 or int(events.y.max()) > 2047):
        raise EventDataError("event x/y above 2047 cannot be encoded (11-bit fields)")
    if len(triggers) and int(triggers.channel.max()) > max_channel:
        raise EventDataError(f"trigger channel above {max_channel} cannot be encoded")


class Evt3Encoder:
    """Streaming EVT 3.0 encoder: successive `encode` calls continue one byte stream.

    Same-time, same-row, same-polarity runs of increasing x (what a sensor readout produces)
    become VECT_BASE_X + VECT_12/VECT_8 words; isolated events become EVT_ADDR_X. TIME_HIGH is
    stepped by at most 2047 units so a decoder always recognises roll-overs; the stream starts
    with time base 0, as a freshly reset camera does.
    """

    def __init__(self) -> None:
        self._state = np.array([0, 0, -1, -1], np.int64)
        self._last_t = 0

    def encode(self, events: EventArray, triggers: TriggerEvents | None = None) -> bytes:
        trig = triggers if triggers is not None else TriggerEvents.empty()
        _check_inputs(events, trig, self._last_t, 0xF)
        if len(events) and int(events.t[0]) < 0:
            raise EventDataError("negative event time cannot be encoded")
        args = (events.x, events.y, events.p, events.t, trig.t, trig.p, trig.channel)
        nwords = encode_kernel(*args, self._state.copy(), np.empty(0, np.uint16), False)
        out = np.empty(nwords, np.uint16)
        encode_kernel(*args, self._state, out, True)
        if len(events):
            self._last_t = max(self._last_t, int(events.t[-1]))
        if len(trig):
            self._last_t = max(self._last_t, int(trig.t[-1]))
        return out.astype("<u2", copy=False).tobytes()


def encode_evt3(events: EventArray, triggers: TriggerEvents | None = None) -> bytes:
    """One-shot EVT 3.0 encoding of a whole recording."""
    return Evt3Encoder().encode(events, triggers)
