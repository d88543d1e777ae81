"""The voxel grid's per-event work as numba kernels (nogil), for CPU training jobs.

`representations.voxel_grid` is the front: it checks its arguments and calls these. One pass
over the events scatters each polarity into its two nearest time bins of a float32 grid, with
the window and sensor bounds checked per event, so no filtered copy of the events, no float64
grid of twice the size and no index arrays are made (the numpy reference,
`representations.voxel_grid_bincount`, makes all three; `python -m bench.training_reader`
times both). Bin positions are computed exactly as the reference does them (float64 of the
int64 time since the window start, divided by the duration, times B - 1), so every event lands
in the same bins with the same weights; only the accumulation is float32.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray


@njit(nogil=True, cache=True, inline="always")
def _split(  # pragma: no cover - numba
    ti: int, t0: int, duration: float, span: float, bins: int
) -> tuple[int, int, float]:
    """The two bins an event's polarity is split between, and the later one's share: one
    place for both kernels, so their grids stay bit-identical."""
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
) -> int:
    """Add the events with t0 <= t <= t1 on the sensor into `out` ((bins, height, width),
    float32, C order); returns how many were added."""
    duration = float(max(t1 - t0, 1))
    span = float(bins - 1)
    added = 0
    for i in range(t.shape[0]):
        ti = t[i]
        xi = int(x[i])
        yi = int(y[i])
        if ti < t0 or ti > t1 or xi >= width or yi >= height:
            continue
        pol = np.float64(p[i])
        added += 1
        if bins == 1:
            out[0, yi, xi] += np.float32(pol)
            continue
        lo, hi, frac = _split(ti, t0, duration, span, bins)
        out[lo, yi, xi] += np.float32(pol * (1.0 - frac))
        out[hi, yi, xi] += np.float32(pol * frac)
    return added


@njit(nogil=True, cache=True)
def voxel_accumulate_tracked(
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
    """`voxel_accumulate` into the flat `out`, recording every flat index it adds to in
    `touched` (room for 2 per event); returns how many it recorded. The same bins, weights and
    order of additions as `voxel_accumulate`, so the grids are bit-identical."""
    duration = float(max(t1 - t0, 1))
    span = float(bins - 1)
    npix = width * height
    k = 0
    for i in range(t.shape[0]):
        ti = t[i]
        xi = int(x[i])
        yi = int(y[i])
        if ti < t0 or ti > t1 or xi >= width or yi >= height:
            continue
        pol = np.float64(p[i])
        pix = yi * width + xi
        if bins == 1:
            out[pix] += np.float32(pol)
            touched[k] = pix
            k += 1
            continue
        lo, hi, frac = _split(ti, t0, duration, span, bins)
        out[lo * npix + pix] += np.float32(pol * (1.0 - frac))
        out[hi * npix + pix] += np.float32(pol * frac)
        touched[k] = lo * npix + pix
        touched[k + 1] = hi * npix + pix
        k += 2
    return k


@njit(nogil=True, cache=True)
def reset_entries(out: NDArray[np.float32], touched: NDArray[np.int64], k: int) -> None:
    """Zero the first `k` recorded flat indices of `out`."""
    for i in range(k):
        out[touched[i]] = 0


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
