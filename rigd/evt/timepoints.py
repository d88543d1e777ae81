# mypy: disable-error-code="no-any-return,assignment,arg-type"
"""Stream time at byte positions of an EVT 3.0 / EVT 2.0 stream, from its time words alone.

A replay that hands out a recording's bytes as a device would (paced against the host clock)
must know, for a byte offset, how far the stream's time has got there without decoding it.
One pass over the words (numba) reads the time words (EVT 3.0 TIME_HIGH and TIME_LOW, EVT 2.0
TIME_HIGH), follows the counter's roll-over, and keeps a point per `grain` microseconds of
stream time: (offset of the first word whose time reaches a new grain, grain start). Every
word before a point's offset has a time below that point's time, so bytes cut at a point are
never ahead of it. Time that falls (a jump back in time, a corrupt word) holds the running
maximum until the stream passes it again: such bytes are paced as if they had no time. An EVT 3.0
TIME_HIGH the decoder judges corrupt (a large step the next TIME_HIGH refutes, `evt3._refuted`)
is skipped here as there: taken, its step forward would have held every later byte back until
the host clock caught up with it (and a step past half the counter counted as a roll-over).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit
from numpy.typing import NDArray

from rigd.core.errors import EventDataError
from rigd.evt.evt3 import TH_JUMP, _refuted

#: Point spacing (us): one EVT 2.0 TIME_HIGH period; 64 of them make an EVT 3.0 TIME_HIGH period.
GRAIN_US = 64


@njit(nogil=True, cache=True, inline="always")
def _reach(
    t: int,
    i: int,
    grain: int,
    off: NDArray[np.int64],
    tp: NDArray[np.int64],
    fill: bool,
    n: int,
    tmax: int,
    bucket: int,
) -> tuple[int, int, int]:  # pragma: no cover - numba
    """Word i has time t: a new point when t passes the running maximum into a new grain.
    Returns (points, running maximum, grain of the last point)."""
    if t > tmax:
        tmax = t
        b = t // grain
        if b > bucket:
            bucket = b
            if fill:
                off[n] = i
                tp[n] = b * grain
            n += 1
    return n, tmax, bucket


# One kernel per format, alike in shape on purpose: each reads its own word size and time
# words with no per-word format branch; what they share is `_reach`.
@njit(nogil=True, cache=True)
def _evt3_points(
    words: NDArray[np.uint16], grain: int, off: NDArray[np.int64], tp: NDArray[np.int64], fill: bool
) -> tuple[int, int]:  # pragma: no cover - numba
    n = 0
    started = False
    th = 0
    loop = 0
    tmax = -1
    bucket = -1
    for i in range(words.shape[0]):
        w = np.int64(words[i])
        typ = w >> 12
        if typ == 0x8:
            v = w & 0xFFF
            if started and ((v - th) & 0xFFF) > TH_JUMP and _refuted(words, i, th, v):
                continue  # a corrupt TIME_HIGH, as the decoder judges it: it drops the word too
            if started and v < th and th - v >= 2048:
                loop += 1
            th = v
            started = True
            t = (loop << 24) | (th << 12)
        elif typ == 0x6 and started:
            t = (loop << 24) | (th << 12) | (w & 0xFFF)
        else:
            continue
        n, tmax, bucket = _reach(t, i, grain, off, tp, fill, n, tmax, bucket)
    return n, tmax


@njit(nogil=True, cache=True)
def _evt2_points(
    words: NDArray[np.uint32], grain: int, off: NDArray[np.int64], tp: NDArray[np.int64], fill: bool
) -> tuple[int, int]:  # pragma: no cover - numba
    n = 0
    started = False
    th = 0
    loop = 0
    tmax = -1
    bucket = -1
    for i in range(words.shape[0]):
        w = np.int64(words[i])
        if (w >> 28) != 0x8:
            continue
        v = w & 0x0FFFFFFF
        if started and v < th and th - v >= (1 << 27):
            loop += 1
        th = v
        started = True
        t = (loop << 34) | (th << 6)
        n, tmax, bucket = _reach(t, i, grain, off, tp, fill, n, tmax, bucket)
    return n, tmax


#: Word size (bytes) and word dtype of the formats whose time words `time_points` reads.
WORDS: dict[str, tuple[int, np.dtype[Any]]] = {"evt3": (2, np.dtype("<u2")), "evt2": (4, np.dtype("<u4"))}


def time_points(
    words: NDArray[np.uint16] | NDArray[np.uint32], fmt: str, grain: int = GRAIN_US
) -> tuple[NDArray[np.int64], NDArray[np.int64], int]:
    """(byte offsets, times in us, last time) of the stream's points, times absolute in the
    stream's clock (roll-overs unwrapped). Empty arrays and -1 when it holds no time word."""
    if fmt not in WORDS:
        raise EventDataError(f"time points: EVT format {fmt!r} not supported (only {sorted(WORDS)})")
    if grain < 1:
        raise EventDataError(f"time points: grain {grain} us must be >= 1")
    kernel = _evt3_points if fmt == "evt3" else _evt2_points
    empty = np.empty(0, np.int64)
    n, _ = kernel(words, grain, empty, empty, False)
    off, tp = np.empty(n, np.int64), np.empty(n, np.int64)
    _, last = kernel(words, grain, off, tp, True)
    return off * WORDS[fmt][0], tp, int(last)
