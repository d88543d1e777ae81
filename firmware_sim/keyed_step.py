"""The simulator's threaded step: events emitted as packed int64 keys per block of rows and
bucketed by coarse time, then counting-sorted per bucket into the output columns, on numba's
threads (`prange`, nogil) or their serial twins; and `sort_by_time` for the serial paths."""

from __future__ import annotations

import types
from collections.abc import Callable
from typing import Any

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from firmware_sim.pixel_kernels import (
    F64,
    I64,
    EventOut,
    Frame,
    LogInput,
    Pixels,
    StepParams,
    crossings,
    event_time,
    filtered,
    level_gain,
)
from rigd.core.events import EventArray

# The simulator's step runs in two passes over fixed blocks of rows, so that the events
# come out in the order of the reference (stable by time: raster order, then the noise)
# whatever the number of threads. Between passes an event is one int64 key,
# (t - t0 - 1) << KEY_T_SHIFT | y << 17 | x << 1 | (ON), 8 bytes to move:
# 1. emit: each block of rows runs the per-pixel rule, appends its events' keys (raster
#    order) to its own slice of a scratch buffer, counts them per coarse time bucket and
#    advances its pixels' state; a block whose slice is full stops before a pixel and
#    resumes there once the buffer has grown. A finished block sorts its keys by coarse
#    bucket (stable, while they are still in cache) into its slice of a second buffer;
# 2. sort: each coarse bucket gathers its run of keys from every block in order (the
#    noise's last), sorts them by the fine time (counting sort, stable) and unpacks them
#    into its range of the output columns.
# Each pass is a `prange` over blocks (or buckets) calling a per-block kernel, compiled
# twice from one source (`_threaded_and_serial`): the `_par` variant on numba's threads, the
# `_ser` variant running the same blocks in order on one thread.

#: Rows of the image are cut into at most this many blocks (the unit of parallel work).
MAX_BLOCKS = 64
#: At most 2**COARSE_BITS coarse time buckets per step.
COARSE_BITS = 7
#: Bit of an event key where its time (relative to the step's start) begins.
KEY_T_SHIFT = 33
#: Steps at least this long (us, ~18 min) run the serial reference (times must fit a key).
MAX_KEYED_SPAN = 1 << 30


# numba kernels take every array as a parameter of its own (no objects), so their signatures
# here and in event_kernels are long lists alike in shape; there is nothing to share.
@njit(nogil=True, cache=True)
def _emit_block(  # pragma: no cover - numba
    b: int,
    rows: int,
    frame: Frame,
    conv: LogInput,
    px: Pixels,
    prm: StepParams,
    t0: int,
    t1: int,
    shift: int,
    hist: I64,
    filled: I64,
    resume: I64,
    keys: I64,
    bucketed: I64,
    table: F64,
) -> None:
    """Pass 1 for block b (rows [b*rows, (b+1)*rows)) from flat pixel index resume[b].

    A uint8 frame is read through `table` (`level_table`: log level and low-pass gain
    per value, the same numbers), any other through `level_gain`.

    Event keys go to keys[b*cap + filled[b]:(b+1)*cap] (cap = len(keys) // len(filled)),
    counted in hist[b]; the arithmetic is `step_kernel`'s. Stops before a pixel whose
    events do not fit, leaving its index in resume[b]; else resume[b] = the block's end
    and the block's keys, sorted by coarse bucket, are in the same slice of `bucketed`.
    """
    level, ref, thr_on, thr_off, last_t = px
    leak_rate_hz = prm[0]
    lowpass = prm[1]
    refractory_us = prm[4]
    use_table = table.shape[1] == 256  # a uint8 frame (else the table is empty)
    h, w = frame.shape
    cap = keys.shape[0] // filled.shape[0]
    lo = b * cap
    n = filled[b]
    dt = float(t1 - t0)
    dt_s = dt * 1e-6
    base = t0 + 1
    i_end = min(h, (b + 1) * rows)
    i0 = resume[b] // w
    j0 = resume[b] - i0 * w
    for i in range(i0, i_end):
        for j in range(j0 if i == i0 else 0, w):
            lp = level[i, j]
            if use_table:
                v = int(frame[i, j])
                ln = filtered(lp, table[0, v], table[1, v], lowpass)
            else:
                lv, a = level_gain(frame[i, j], conv, prm, dt_s)
                ln = filtered(lp, lv, a, lowpass)
            r = ref[i, j]
            k, sign, c, d0, slope, drift = crossings(
                lp, ln, r, thr_on[i, j], thr_off[i, j], leak_rate_hz, dt_s
            )
            if k > 0:
                if n + k > cap:
                    filled[b] = n
                    resume[b] = i * w + j
                    return
                lt = last_t[i, j]
                pix = (i << 17) | (j << 1) | (1 if sign > 0 else 0)
                for m in range(1, k + 1):
                    te = event_time(m, sign, c, d0, slope, t0, t1, dt)
                    if te - lt < refractory_us:
                        continue
                    keys[lo + n] = ((te - base) << KEY_T_SHIFT) | pix
                    n += 1
                    hist[b, (te - base) >> shift] += 1
                    lt = te
                last_t[i, j] = lt
                r += sign * k * c
            level[i, j] = ln
            if k > 0 or drift != 0.0:
                ref[i, j] = r - drift
    filled[b] = n
    resume[b] = i_end * w
    _bucket_sort(keys, lo, n, hist[b], shift, bucketed)


@njit(nogil=True, cache=True)
def _bucket_sort(  # pragma: no cover - numba
    keys: I64, lo: int, n: int, counts: I64, shift: int, dst: I64
) -> None:
    """keys[lo:lo+n] into dst[lo:lo+n] by coarse bucket (stable); counts: keys per bucket."""
    pos = np.empty(counts.shape[0], np.int64)
    acc = lo
    for q in range(counts.shape[0]):
        pos[q] = acc
        acc += counts[q]
    sh = KEY_T_SHIFT + shift
    for e in range(lo, lo + n):
        key = keys[e]
        q = key >> sh
        dst[pos[q]] = key
        pos[q] += 1


@njit(nogil=True, cache=True, inline="always")
def _unpack(key: int, base: int, e: int, out: EventOut) -> None:
    ox, oy, op, ot = out
    ox[e] = (key >> 1) & 0xFFFF
    oy[e] = (key >> 17) & 0xFFFF
    op[e] = 1 if key & 1 else -1
    ot[e] = base + (key >> KEY_T_SHIFT)


@njit(nogil=True, cache=True)
def _sort_bucket(  # pragma: no cover - numba
    q: int,
    bounds: I64,
    starts: I64,
    hist: I64,
    base: int,
    shift: int,
    bucketed: I64,
    noise: I64,
    out: EventOut,
) -> None:
    """Pass 2 for coarse bucket q: its keys, from every block's run (starts[b, q], hist[b, q]
    long, in `bucketed`; the last row's in `noise`), sorted by time into out[bounds[q]:bounds[q+1]]."""
    lo = bounds[q]
    n = bounds[q + 1] - lo
    if n == 0:
        return
    n_runs = hist.shape[0]
    span = 1 << shift
    if n == 1 or span == 1:
        e = lo
        for b in range(n_runs):
            src = noise if b == n_runs - 1 else bucketed
            for s in range(starts[b, q], starts[b, q] + hist[b, q]):
                _unpack(src[s], base, e, out)
                e += 1
        return
    if span <= 4 * n + 64:
        mask = span - 1
        counts = np.zeros(span + 1, np.int64)
        for b in range(n_runs):
            src = noise if b == n_runs - 1 else bucketed
            for s in range(starts[b, q], starts[b, q] + hist[b, q]):
                counts[((src[s] >> KEY_T_SHIFT) & mask) + 1] += 1
        for f in range(1, span + 1):
            counts[f] += counts[f - 1]
        # Sort the keys in a local buffer (one write stream per fine bucket, in cache), then
        # unpack them in order (one sequential stream per output column).
        local = np.empty(n, np.int64)
        for b in range(n_runs):
            src = noise if b == n_runs - 1 else bucketed
            for s in range(starts[b, q], starts[b, q] + hist[b, q]):
                key = src[s]
                f = (key >> KEY_T_SHIFT) & mask
                local[counts[f]] = key
                counts[f] += 1
        for e in range(n):
            _unpack(local[e], base, lo + e, out)
        return
    gathered = np.empty(n, np.int64)
    e = 0
    for b in range(n_runs):
        src = noise if b == n_runs - 1 else bucketed
        for s in range(starts[b, q], starts[b, q] + hist[b, q]):
            gathered[e] = src[s]
            e += 1
    order = np.argsort(gathered >> KEY_T_SHIFT, kind="mergesort")
    for e in range(n):
        _unpack(gathered[order[e]], base, lo + e, out)


def _threaded_and_serial(f: Callable[..., None]) -> tuple[Any, Any]:
    """`f` compiled twice: with `parallel=True`, its `prange` loop runs over numba's
    threads; without, `prange` runs as `range`, in order on the calling thread.

    Each variant is compiled from its own copy of `f`, named `<f>_par` and
    `<f>_ser`: numba's on-disk cache files a function under its module, qualified name
    and first line, and within that by signature, CPU and bytecode, not by `parallel`, so two
    dispatchers of one function would share one cache entry and one of them would load the
    other's code (the serial twin the threaded code, or the other way round).
    """

    def compiled(suffix: str, parallel: bool) -> Any:
        twin = types.FunctionType(
            f.__code__, f.__globals__, f.__name__ + suffix, f.__defaults__, f.__closure__
        )
        twin.__qualname__ = f.__qualname__ + suffix
        twin.__doc__ = f.__doc__
        return njit(nogil=True, cache=True, parallel=parallel)(twin)

    return compiled("_par", True), compiled("_ser", False)


def _emit(  # pragma: no cover - numba
    frame: Frame,
    conv: LogInput,
    px: Pixels,
    prm: StepParams,
    t0: int,
    t1: int,
    rows: int,
    shift: int,
    hist: I64,
    filled: I64,
    resume: I64,
    keys: I64,
    bucketed: I64,
    table: F64,
) -> None:
    """Pass 1: `_emit_block` for every block."""
    for b in prange(filled.shape[0]):
        _emit_block(b, rows, frame, conv, px, prm, t0, t1, shift, hist, filled, resume, keys, bucketed, table)


def _sort(  # pragma: no cover - numba
    bounds: I64, starts: I64, hist: I64, base: int, shift: int, bucketed: I64, noise: I64, out: EventOut
) -> None:
    """Pass 2: `_sort_bucket` for every coarse bucket."""
    for q in prange(bounds.shape[0] - 1):
        _sort_bucket(q, bounds, starts, hist, base, shift, bucketed, noise, out)


_emit_par, _emit_ser = _threaded_and_serial(_emit)
_sort_par, _sort_ser = _threaded_and_serial(_sort)


@njit(nogil=True, cache=True)
def _run_offsets(hist: I64, cap: int) -> tuple[I64, I64]:  # pragma: no cover - numba
    """(bounds, starts) of a (runs, buckets) histogram: bucket q's events go to the output's
    [bounds[q], bounds[q + 1]); run b's keys of bucket q start at starts[b, q] (run b of the
    key buffer at b * cap, the last run, the noise's, at 0 of its own array)."""
    n_r, n_q = hist.shape
    bounds = np.empty(n_q + 1, np.int64)
    pos = 0
    for q in range(n_q):
        bounds[q] = pos
        for b in range(n_r):
            pos += hist[b, q]
    bounds[n_q] = pos
    starts = np.empty((n_r, n_q), np.int64)
    for b in range(n_r):
        acc = b * cap if b < n_r - 1 else 0
        for q in range(n_q):
            starts[b, q] = acc
            acc += hist[b, q]
    return bounds, starts


@njit(nogil=True, cache=True)
def _noise_keys(ev: EventOut, base: int, shift: int, counts: I64) -> I64:  # pragma: no cover - numba
    """Keys of extra events (in their order), counted per coarse bucket into `counts`."""
    x, y, p, t = ev
    keys = np.empty(t.shape[0], np.int64)
    for e in range(t.shape[0]):
        rel = t[e] - base
        counts[rel >> shift] += 1
        keys[e] = (
            (rel << KEY_T_SHIFT) | (np.int64(y[e]) << 17) | (np.int64(x[e]) << 1) | (1 if p[e] > 0 else 0)
        )
    return keys


@njit(nogil=True, cache=True)
def _counting_sort(  # pragma: no cover - numba
    x: NDArray[np.uint16], y: NDArray[np.uint16], p: NDArray[np.int8], t: I64, t_lo: int, span: int
) -> tuple[NDArray[np.uint16], NDArray[np.uint16], NDArray[np.int8], I64]:
    """Stable sort by t of events whose times lie in [t_lo, t_lo + span)."""
    n = t.shape[0]
    counts = np.zeros(span + 1, np.int64)
    for i in range(n):
        counts[t[i] - t_lo + 1] += 1
    for b in range(1, span + 1):
        counts[b] += counts[b - 1]
    ox = np.empty(n, np.uint16)
    oy = np.empty(n, np.uint16)
    op = np.empty(n, np.int8)
    ot = np.empty(n, np.int64)
    for i in range(n):
        b = t[i] - t_lo
        dst = counts[b]
        counts[b] += 1
        ox[dst] = x[i]
        oy[dst] = y[i]
        op[dst] = p[i]
        ot[dst] = t[i]
    return ox, oy, op, ot


def _event_arrays(n: int) -> EventOut:
    return np.empty(n, np.uint16), np.empty(n, np.uint16), np.empty(n, np.int8), np.empty(n, np.int64)


def sort_by_time(
    x: NDArray[np.uint16], y: NDArray[np.uint16], p: NDArray[np.int8], t: I64, t_lo: int, t_hi: int
) -> EventArray:
    """Events sorted by time (stable), as new arrays; all t must lie in [t_lo, t_hi].

    Counting sort when the time span is not much larger than the event count (the usual
    case for short steps), else numpy's stable argsort.
    """
    n = t.shape[0]
    if n == 0:
        return EventArray.empty()
    span = t_hi - t_lo + 1
    if span <= 8 * n + 4096:
        return EventArray(*_counting_sort(x, y, p, t, t_lo, span))
    order = np.argsort(t, kind="stable")
    return EventArray(x[order], y[order], p[order], t[order])
