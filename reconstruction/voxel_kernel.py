"""The voxel grid's per-event work as numba kernels (nogil), for CPU training jobs.

`representations.voxel_grid` is the front: it checks its arguments and calls these. One pass
over the events scatters each polarity into its two nearest time bins of a float32 grid, with
the window and sensor bounds checked per event, so no filtered copy of the events, no float64
grid of twice the size and no index arrays are made (the numpy reference,
`representations.voxel_grid_bincount`, makes all three; `python -m bench.training_reader`
times both). Bin positions are computed exactly as the reference does them (float64 of the
int64 time since the window start, divided by the duration, times B - 1), so every event lands
in the same bins with the same weights; only the accumulation is float32.

The grid is addressed flat with unsigned indices: numba then emits neither negative-index
wrap-around nor per-axis strides, which made the scatter into a cached grid ~1.7x faster (it
is bound by the grid's memory, not by the arithmetic). At 1280x720x5 the grid is 18.4 MB:
zeroing it costs as much as the events do; `clear` zeroes a reused grid by reading it and
writing back only the blocks that are not zero, no dearer than a full write and cheaper when
most of it is zero.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

#: Words (uint32) per block `clear` tests at once: 512 bytes, 8 cache lines. Long enough for the
#: test to be vector code; one 64-byte line per block was slower than `fill(0)` here.
_BLOCK = 128


@njit(nogil=True, cache=True, inline="always")
def _split(  # pragma: no cover - numba
    ti: int, t0: int, duration: float, span: float, bins: int
) -> tuple[int, int, float]:
    """The two bins an event's polarity is split between, and the later one's share: one
    place for every kernel, so their grids stay bit-identical."""
    tn = (float(ti - t0) / duration) * span
    lo = min(max(int(np.floor(tn)), 0), bins - 1)
    return lo, min(lo + 1, bins - 1), tn - lo


@njit(nogil=True, cache=True)
def voxel_accumulate(
    x: NDArray[np.uint16],
    y: NDArray[np.uint16],
    p: NDArray[np.int8],
    t: NDArray[np.int64],
    t0: int,
    t1: int,
    width: int,
    height: int,
    bins: int,
    out: NDArray[np.float32],
    touched: NDArray[np.int64],
) -> int:
    """Add the events with t0 <= t <= t1 on the sensor into the flat `out` (a C-order
    (bins, height, width) float32 grid, raveled); returns how many entries it added to.

    When `touched` has room (2 per event), every flat index added to is recorded there, so the
    caller can reset just those; an empty `touched` records nothing. Additions are made in event
    order, so the grid is the same bit for bit either way."""
    duration = float(max(t1 - t0, 1))
    span = float(bins - 1)
    npix = width * height
    track = touched.shape[0] > 0
    k = 0
    for i in range(t.shape[0]):
        ti = t[i]
        xi = np.intp(x[i])
        yi = np.intp(y[i])
        if ti < t0 or ti > t1 or xi >= width or yi >= height:
            continue
        pol = np.float64(p[i])
        pix = yi * width + xi
        if bins == 1:
            out[np.uintp(pix)] += np.float32(pol)
            if track:
                touched[k] = pix
            k += 1
            continue
        lo, hi, frac = _split(ti, t0, duration, span, bins)
        a = np.uintp(lo * npix + pix)  # unsigned: no wrap-around code for negative indices
        b = np.uintp(hi * npix + pix)
        out[a] += np.float32(pol * (1.0 - frac))
        out[b] += np.float32(pol * frac)
        if track:
            touched[k] = a
            touched[k + 1] = b
        k += 2
    return k


@njit(nogil=True, cache=True)
def reset_entries(out: NDArray[np.float32], touched: NDArray[np.int64], k: int) -> None:
    """Zero the first `k` recorded flat indices of the flat `out`."""
    for i in range(k):
        out[np.uintp(touched[i])] = 0


@njit(nogil=True, cache=True)
def clear(words: NDArray[np.uint32]) -> None:
    """All bits of `words` (a grid viewed as uint32) to zero, writing only the blocks that are
    not already zero: a reused, mostly empty grid is read, not rewritten. Bits, not floats,
    are compared, so -0.0 and NaN are cleared too: the result is exactly `fill(0)`."""
    n = words.shape[0]
    full = n - n % _BLOCK
    for s in range(0, full, _BLOCK):
        acc = np.uint32(0)
        for j in range(s, s + _BLOCK):
            acc |= words[j]
        if acc != 0:
            for j in range(s, s + _BLOCK):
                words[j] = 0
    for j in range(full, n):
        words[j] = 0


@njit(nogil=True, cache=True)
def standardize_nonzero(out: NDArray[np.float32]) -> None:
    """Non-zero entries to zero mean and unit (population) std, in place; zeros stay zero.

    Two passes with float64 sums, as numpy's mean and std of the non-zero entries."""
    flat = out.reshape(-1)
    n = 0
    total = 0.0
    for v in flat:
        if v != 0:
            n += 1
            total += float(v)
    if n == 0:
        return
    mean = total / n
    sq = 0.0
    for v in flat:
        if v != 0:
            d = float(v) - mean
            sq += d * d
    std = np.sqrt(sq / n)
    if not std > 0:
        std = 1.0
    for i in range(flat.shape[0]):
        if flat[i] != 0:
            flat[i] = np.float32((flat[i] - mean) / std)
