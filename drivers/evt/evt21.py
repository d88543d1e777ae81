# mypy: disable-error-code="arg-type,assignment,call-arg"
"""EVT 2.1 (64-bit words, 32-pixel validity masks) decoder kernels and encoder, OpenEB semantics.

Each 64-bit word has its type, ts (6 bits), x base (11 bits) and y (11 bits) in the upper 32 bits
(same bit positions as EVT 2.0) and a 32-bit validity mask in the lower 32 bits: pixel
x_base + i fired when bit i is set. Two byte layouts exist: IMX636 sends the upper half first
(each half little-endian, "half-swapped", fmt "evt21"); GenX320 sends the whole 64-bit word
little-endian (lower half first, fmt "evt21_le"). Time handling is EVT 2.0's, and so are the
decode kernels: `evt2`'s factory built for masked words.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

from drivers.evt import evt2
from drivers.evt.evt2 import TH_STEP
from drivers.evt.evt3 import _check_inputs
from rigd.core.errors import EventDataError
from rigd.core.events import EventArray, TriggerEvents

WORD_BYTES = 8
MAX_EVENTS_PER_WORD = 32
STATE_SIZE = evt2.STATE_SIZE
new_decoder_state = evt2.new_decoder_state  # EVT 2.0's time state: started, loop, time_high

# the kernels read a word as two u32 halves: buf[2 * pos], buf[2 * pos + 1]
decode_kernel = evt2.make_decode_kernel(masked=True, swapped=True)
decode_kernel_le = evt2.make_decode_kernel(masked=True, swapped=False)


@njit(nogil=True, cache=True)
def _put(out: NDArray[np.uint32], k: int, hi: int, lo: int, swapped: bool, write: bool) -> int:
    if write:
        if swapped:
            out[2 * k] = hi
            out[2 * k + 1] = lo
        else:
            out[2 * k] = lo
            out[2 * k + 1] = hi
    return k + 1


@njit(nogil=True, cache=True)
def _emit_time(
    out: NDArray[np.uint32], k: int, st: NDArray[np.int64], tv: int, swapped: bool, write: bool
) -> int:
    thf = tv >> 6
    if st[0] == 0:
        first = min(thf, TH_STEP)
        k = _put(out, k, (0x8 << 28) | first, 0, swapped, write)
        st[0] = 1
        st[1] = first
    while st[1] < thf:
        st[1] += min(thf - st[1], TH_STEP)
        k = _put(out, k, (0x8 << 28) | (st[1] & 0xFFFFFFF), 0, swapped, write)
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
    swapped: bool,
    write: bool,
) -> int:
    """Encode time-sorted events (same t/y/p, increasing x within one 32-pixel group share a
    word) and triggers; out holds two u32 per word in transmission order. write=False counts."""
    ne = t.shape[0]
    ntr = tt.shape[0]
    i = 0
    j = 0
    k = 0
    while i < ne or j < ntr:
        if j < ntr and (i >= ne or tt[j] <= t[i]):
            k = _emit_time(out, k, st, tt[j], swapped, write)
            hi = (
                (0xA << 28) | ((tt[j] & 0x3F) << 22) | ((np.int64(tc[j]) & 0x1F) << 8) | (np.int64(tp[j]) & 1)
            )
            k = _put(out, k, hi, 0, swapped, write)
            j += 1
            continue
        tv = t[i]
        xb = np.int64(x[i]) & ~31
        e = i + 1
        while (
            e < ne
            and t[e] == tv
            and y[e] == y[i]
            and p[e] == p[i]
            and x[e] > x[e - 1]
            and (np.int64(x[e]) & ~31) == xb
        ):
            e += 1
        mask = 0
        for q in range(i, e):
            mask |= 1 << (np.int64(x[q]) - xb)
        k = _emit_time(out, k, st, tv, swapped, write)
        typ = 1 if p[i] > 0 else 0
        hi = (typ << 28) | ((tv & 0x3F) << 22) | (xb << 11) | np.int64(y[i])
        k = _put(out, k, hi, mask, swapped, write)
        i = e
    return k


class Evt21Encoder:
    """Streaming EVT 2.1 encoder (IMX636 half-swapped layout unless little_endian=True)."""

    def __init__(self, *, little_endian: bool = False) -> None:
        self._swapped = not little_endian
        self._state = np.zeros(2, np.int64)
        self._last_t = 0

    def encode(self, events: EventArray, triggers: TriggerEvents | None = None) -> bytes:
        trig = triggers if triggers is not None else TriggerEvents.empty()
        _check_inputs(events, trig, self._last_t, 0x1F)
        if len(events) and int(events.t[0]) < 0:
            raise EventDataError("negative event time cannot be encoded")
        args = (events.x, events.y, events.p, events.t, trig.t, trig.p, trig.channel)
        nwords = encode_kernel(*args, self._state.copy(), np.empty(0, np.uint32), self._swapped, False)
        out = np.empty(2 * nwords, np.uint32)
        encode_kernel(*args, self._state, out, self._swapped, True)
        for arr in (events.t, trig.t):
            if arr.size:
                self._last_t = max(self._last_t, int(arr[-1]))
        return out.astype("<u4", copy=False).tobytes()


def encode_evt21(
    events: EventArray, triggers: TriggerEvents | None = None, *, little_endian: bool = False
) -> bytes:
    """One-shot EVT 2.1 encoding of a whole recording."""
    return Evt21Encoder(little_endian=little_endian).encode(events, triggers)
