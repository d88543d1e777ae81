"""Motion-aware partitioning into segments with canonical keyframes (paper Sec. 3.3).

One 4D deformation field can only explain a limited amount of motion, so the sequence is cut
into segments whose motion stays under a budget. Event activity measures motion: the stream is
binned into short windows (`window_us`), and a segment is closed when

    instant_weight * activity(window) + accumulated activity since the segment start > threshold

with activity in events per pixel (so thresholds do not depend on the resolution). A static
scene (only noise) never reaches the threshold and stays one segment; fast motion fills the
budget quickly and gives more, shorter segments; a burst in one window (instant term) closes a
segment at once. `min_segment_us` stops noise bursts from shattering the sequence.

Canonical keyframe: among the candidate times tau_i of a segment (frame times inside it, or the
window ends when none are given), tau* = argmin_i sum_j ||E(tau_i) - E(tau_j)||_1 with E(tau)
the accumulated signed event map from the segment start to tau (computed at reduced resolution:
`map_scale`), i.e. the time closest to the segment's "event mean".
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rigd.core.events import EventArray

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class Segment:
    """[t_start_us, t_end_us) of one motion-consistent segment and its canonical keyframe."""

    index: int
    t_start_us: int
    t_end_us: int
    keyframe_us: int
    n_events: int
    activity: float
    """Events per pixel inside the segment."""


@dataclass(frozen=True, slots=True)
class PartitionConfig:
    window_us: int = 5_000
    threshold: float = 2.0
    """Budget of accumulated activity per segment, events per pixel."""
    instant_weight: float = 1.0
    min_segment_us: int = 10_000
    map_scale: float = 0.25


def window_counts(events: EventArray, t0_us: int, t1_us: int, window_us: int) -> NDArray[np.int64]:
    """Event count per window [t0 + k w, t0 + (k+1) w) covering [t0, t1)."""
    n_win = max(1, -(-(t1_us - t0_us) // window_us))
    k = (events.t - np.int64(t0_us)) // window_us
    k = k[(k >= 0) & (k < n_win)]
    return np.bincount(k, minlength=n_win).astype(np.int64)


def segment_starts(counts: NDArray[np.int64], n_pix: int, cfg: PartitionConfig) -> list[int]:
    """Window indices where segments start (first is 0). Loop over windows, not events.

    Causal: a boundary depends only on the windows up to it. `n_pix` is the pixel count the
    counts come from (all sensors' pixels for a rig-level segmentation), so the budget stays in
    events per pixel whatever the resolution and sensor count.
    """
    act = counts.astype(np.float64) / n_pix
    starts = [0]
    acc = 0.0
    min_w = max(1, -(-cfg.min_segment_us // cfg.window_us))
    for k in range(len(act)):
        acc += act[k]
        if (
            cfg.instant_weight * act[k] + acc > cfg.threshold
            and k + 1 - starts[-1] >= min_w
            and k + 1 < len(act)
        ):
            starts.append(k + 1)
            acc = 0.0
    return starts


def map_shape(width: int, height: int, scale: float) -> tuple[int, int]:
    """(rows, cols) of the reduced-resolution event maps of a width x height sensor."""
    return max(1, round(height * scale)), max(1, round(width * scale))


def interval_maps(
    events: EventArray, width: int, height: int, cuts: NDArray[np.int64], scale: float
) -> NDArray[np.int32]:
    """(len(cuts) - 1, rows, cols) signed event counts in [cuts[k], cuts[k + 1]) at reduced resolution.

    The increments between keyframe candidates: their prefix sums are the accumulated maps
    E(tau), so a long stream can be summed block by block (`cuts` sorted, events time-sorted).
    """
    sh, sw = map_shape(width, height, scale)
    n_int = max(0, len(cuts) - 1)
    if n_int == 0 or len(events) == 0:
        return np.zeros((n_int, sh, sw), np.int32)
    lo, hi = np.searchsorted(events.t, [cuts[0], cuts[-1]], side="left")
    ev = events[int(lo) : int(hi)]
    k = np.searchsorted(cuts, ev.t, side="right") - 1
    pix = (ev.y.astype(np.int64) * sh // height) * sw + ev.x.astype(np.int64) * sw // width
    inc = np.bincount(k * (sw * sh) + pix, weights=ev.p.astype(np.float64), minlength=n_int * sw * sh)
    return inc.reshape(n_int, sh, sw).astype(np.int32)


def _accumulated_maps(
    events: EventArray, width: int, height: int, t_start: int, taus: NDArray[np.int64], scale: float
) -> NDArray[np.float32]:
    """(n, h, w) signed event maps accumulated from t_start to each tau (downscaled)."""
    sw, sh = max(1, round(width * scale)), max(1, round(height * scale))
    ev = events[(events.t >= t_start) & (events.t <= taus[-1])] if len(events) else events
    k = np.searchsorted(taus, ev.t, side="left")  # first tau >= t: the event counts from that map on
    pix = (ev.y.astype(np.int64) * sh // height) * sw + ev.x.astype(np.int64) * sw // width
    inc = np.bincount(k * (sw * sh) + pix, weights=ev.p.astype(np.float64), minlength=len(taus) * sw * sh)
    return np.cumsum(inc.reshape(len(taus), sh, sw), axis=0).astype(np.float32)


def canonical_keyframe_bruteforce(maps: NDArray[np.floating[Any]]) -> int:
    """Reference: Eq. 3 literally, argmin_i sum_j ||E_i - E_j||_1 over a (n, h, w) stack.

    O(n^2 h w) time: `canonical_keyframe` uses it for a few maps only (up to `_SMALL_N`), the tests
    and `bench.keyframe` compare with it. Ties: the lowest index.
    """
    n = maps.shape[0]
    if n <= 2:  # one map, or two equidistant ones: the first
        return 0
    flat = maps.reshape(n, -1).astype(np.float64)
    v = np.array([np.abs(flat - flat[i]).sum() for i in range(n)])
    return int(np.argmin(v))


_BLOCK_ELEMS = 1 << 20
"""Pixels are processed in column blocks of about this many (map, pixel) elements (bounded memory)."""
_MAX_RECHECK = 64
"""Near-tied candidates (float input) re-evaluated with the reference expression, at most."""
_EXACT_LIMIT = float(2**53)
_SMALL_N = 24
"""Up to this many maps the brute force is used (faster there: ~0.1-0.6 ms at 16x12-80x60 maps)."""


def _deviation_sums(flat: NDArray[Any]) -> NDArray[Any]:
    """V_i = sum_p sum_j |flat[i, p] - flat[j, p]| for a (n, P) int64 or float64 array, O(n log n) per pixel.

    Per pixel the values are sorted (s_0 <= ... <= s_{n-1}, prefix sums S_k = s_0 + ... + s_{k-1}); a
    value x with l values below it and r values at or below it is at distance
    (l x - S_l) + (S_n - S_r - (n - r) x) from all others. Equal values get the same l and r, so equal
    maps get bit-identical V (ties are then broken by index, as the reference does). Float columns are
    shifted by their minimum first, so the prefix sums stay at the scale of the column's range.
    """
    n, n_pix = flat.shape
    integer = np.issubdtype(flat.dtype, np.integer)
    acc_dtype = np.dtype(np.int64) if integer else flat.dtype  # int32 input is summed in int64
    v = np.zeros(n, dtype=acc_dtype)
    cols = max(1, _BLOCK_ELEMS // max(n, 1))
    idx = np.arange(n, dtype=np.int64)
    for c0 in range(0, n_pix, cols):  # blocks of pixels, vectorised inside: no per-map loop
        block = np.ascontiguousarray(flat[:, c0 : c0 + cols].T)  # (pixels, n): sort along rows
        if integer and block.size and block.max() < 2**15:  # values are >= 0 (shifted by the caller)
            block = block.astype(np.int16)  # numpy radix-sorts 16-bit integers (kind="stable")
        elif integer and block.size and block.max() < 2**31:
            block = block.astype(np.int32)
        order = np.argsort(block, axis=1, kind="stable" if block.dtype == np.int16 else None)
        s = np.take_along_axis(block, order, axis=1).astype(acc_dtype)
        s -= s[:, :1]  # shift by the pixel's minimum (exact for int64)
        prefix = np.zeros((s.shape[0], n + 1), dtype=s.dtype)
        np.cumsum(s, axis=1, out=prefix[:, 1:])  # prefix[:, k] = S_k
        if integer:  # exact: using the rank k as l and k + 1 as r gives tied values the same sum
            below = idx * s - prefix[:, :-1]
            above = (prefix[:, -1:] - prefix[:, 1:]) - (n - 1 - idx) * s
        else:  # rounding differs by rank: give a run of equal values its bounds l, r
            new_run = np.ones(s.shape, dtype=bool)
            new_run[:, 1:] = s[:, 1:] != s[:, :-1]
            end_run = np.ones(s.shape, dtype=bool)
            end_run[:, :-1] = new_run[:, 1:]
            lo = np.maximum.accumulate(np.where(new_run, idx, 0), axis=1)  # l: values strictly below
            hi = np.minimum.accumulate(np.where(end_run, idx + 1, n)[:, ::-1], axis=1)[:, ::-1]  # r: <= x
            below = lo * s - np.take_along_axis(prefix, lo, axis=1)
            above = (prefix[:, -1:] - np.take_along_axis(prefix, hi, axis=1)) - (n - hi) * s
        contrib = np.empty_like(s)
        np.put_along_axis(contrib, order, below + above, axis=1)
        v += contrib.sum(axis=0)
    return v


def canonical_keyframe(maps: NDArray[Any], *, small_n: int = _SMALL_N, overwrite: bool = False) -> int:
    """Index of the canonical keyframe (Eq. 3): argmin_i sum_j ||E_i - E_j||_1 over a (n, h, w) stack.

    Same result as `canonical_keyframe_bruteforce` (lowest index among ties) in O(h w n log n) time
    instead of O(h w n^2): the L1 distance splits into pixels and each pixel's sum of absolute
    deviations follows from sorting and prefix sums (`_deviation_sums`).

    Integer-valued maps (what `partition` accumulates: signed event counts) are summed exactly in
    int64, as the reference's float64 sums are exact there. Other input is summed in float64; the
    candidates within a rounding bound of the minimum (normally one) are then re-evaluated with the
    reference's own expression, so near-ties are decided as the reference decides them.
    Up to `small_n` maps the reference itself runs (faster there; tests pass 0 to check the other path).
    `overwrite=True` lets integer maps be shifted in place (no copy of the stack).
    """
    n = maps.shape[0]
    if n <= 2:  # one map, or two equidistant ones: the first
        return 0
    if not np.isfinite(maps).all():
        raise ValueError("event maps must be finite")
    if n <= small_n:  # below the crossover the reference itself is the faster
        return canonical_keyframe_bruteforce(maps)
    if np.issubdtype(maps.dtype, np.integer):  # event counts: exact, summed in int64, no float copy
        ints = maps.reshape(n, -1)
        if overwrite:  # the caller's scratch array: shift it in place instead of copying
            ints -= ints.min(axis=0)
        else:
            ints = ints - ints.min(axis=0)  # one copy, in the input's width (int32 for `interval_maps`)
        return int(np.argmin(_deviation_sums(ints)))
    flat = maps.reshape(n, -1).astype(np.float64)
    n_pix = flat.shape[1]
    low = flat.min(axis=0)
    ranges = flat.max(axis=0) - low
    bound = float(n) * float(ranges.sum())  # >= every V_i
    if bound < _EXACT_LIMIT and bool((flat == np.floor(flat)).all()):
        # integers: flat - low is exact (a result below 2^53), and so is every sum after it
        flat -= low
        return int(np.argmin(_deviation_sums(flat.astype(np.int64))))
    v = _deviation_sums(flat)
    eps = float(np.finfo(np.float64).eps)
    # error of V_fast (cumsum over n terms, n_pix block sums) plus that of the reference (n * n_pix
    # rounded differences, numpy pairwise summation), both relative to `bound`; generous factor 4
    tol = 4.0 * eps * bound * (4 * n + n_pix + 256 + np.log2(float(n) * n_pix))
    cand = np.flatnonzero(v <= v.min() + tol)
    if cand.size == 1:
        return int(cand[0])
    if cand.size > _MAX_RECHECK:  # many maps tied to rounding level: the first of the fast minima
        return int(np.flatnonzero(v == v.min())[0])
    exact = np.array([np.abs(flat - flat[i]).sum() for i in cand])  # the reference's expression
    return int(cand[np.argmin(exact)])


def partition(
    events: EventArray,
    width: int,
    height: int,
    t0_us: int | None = None,
    t1_us: int | None = None,
    *,
    candidate_times_us: Sequence[int] | NDArray[np.int64] | None = None,
    config: PartitionConfig | None = None,
) -> list[Segment]:
    """Segments of [t0, t1) with canonical keyframes, from (denoised, time-sorted) events."""
    cfg = config or PartitionConfig()
    if cfg.window_us <= 0 or cfg.threshold <= 0:
        raise ValueError("window_us and threshold must be positive")
    n = len(events)
    t0 = int(t0_us) if t0_us is not None else (int(events.t[0]) if n else 0)
    t1 = int(t1_us) if t1_us is not None else (int(events.t[-1]) + 1 if n else t0 + cfg.window_us)
    if t1 <= t0:
        raise ValueError(f"empty interval [{t0}, {t1})")
    counts = window_counts(events, t0, t1, cfg.window_us)
    starts = segment_starts(counts, width * height, cfg)
    edges = [t0 + s * cfg.window_us for s in starts] + [t1]
    cand = np.asarray(candidate_times_us if candidate_times_us is not None else [], np.int64)
    segs: list[Segment] = []
    for i in range(len(starts)):
        a, b = edges[i], edges[i + 1]
        taus = cand[(cand >= a) & (cand < b)]
        if taus.size == 0:
            taus = np.arange(a + cfg.window_us, b + cfg.window_us, cfg.window_us, dtype=np.int64)
            taus = np.minimum(taus, b)
            taus = np.unique(taus)
        maps = _accumulated_maps(events, width, height, a, taus, cfg.map_scale)
        key = int(taus[canonical_keyframe(maps)])
        lo, hi = np.searchsorted(events.t, [a, b], side="left")
        ne = int(hi - lo)
        segs.append(Segment(i, a, b, key, ne, ne / (width * height)))
    log.info("partition: %d segments over %.3f s", len(segs), (t1 - t0) * 1e-6)
    return segs


def export_segments(segments: Sequence[Segment], path: str | Path) -> None:
    """Segment boundaries and keyframes as JSON (what the trainer reads)."""
    Path(path).write_text(json.dumps({"segments": [asdict(s) for s in segments]}, indent=2))


def load_segments(path: str | Path) -> list[Segment]:
    return [Segment(**d) for d in json.loads(Path(path).read_text())["segments"]]
