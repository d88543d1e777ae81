"""Representations: exact values on small cases and the extremes of the issue."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from reconstruction.representations import (
    VoxelGridder,
    count_image,
    est_grid,
    event_frame,
    surface_of_active_events,
    time_surface,
    voxel_grid,
    voxel_grid_bincount,
)
from rigd.core.events import EventArray
from tests.reconstruction.parity import assert_voxel_parity

W, H = 6, 5
BIG = 10_000_000_000  # ~2.8 h of microseconds


def ev_of(x: list[int], y: list[int], p: list[int], t: list[int]) -> EventArray:
    return EventArray.from_arrays(x, y, p, t)


def all_reprs(ev: EventArray, t0: int | None = None, t1: int | None = None) -> list[np.ndarray]:
    out = [
        event_frame(ev, W, H, t0, t1),
        count_image(ev, W, H, t0, t1),
        surface_of_active_events(ev, W, H, t0, t1),
        time_surface(ev, W, H, t0, t1, tau_us=50.0),
        voxel_grid(ev, W, H, 5, t0, t1),
        voxel_grid(ev, W, H, 5, t0, t1, normalize=True),
    ]
    out += [est_grid(ev, W, H, 4, t0, t1, kernel=k) for k in ("trilinear", "alpha", "exponential")]
    return out


def test_small_exact() -> None:
    ev = ev_of([1, 1, 2], [0, 0, 3], [1, 1, -1], [BIG, BIG + 50, BIG + 100])
    assert event_frame(ev, W, H)[0, 1] == 2
    assert event_frame(ev, W, H)[3, 2] == -1
    c = count_image(ev, W, H)
    assert c[0, 0, 1] == 2
    assert c[1, 3, 2] == 1
    assert c.sum() == 3
    sae = surface_of_active_events(ev, W, H)
    assert sae[0, 0, 1] == 50
    assert sae[1, 3, 2] == 100
    assert sae[0, 3, 2] == -1
    ts = time_surface(ev, W, H, tau_us=50.0)
    assert ts[1, 3, 2] == pytest.approx(1.0)
    assert ts[0, 0, 1] == pytest.approx(np.exp(-1.0))
    vg = voxel_grid(ev, W, H, 3)  # bins at 0, 50, 100 us
    assert vg[0, 0, 1] == 1
    assert vg[1, 0, 1] == 1
    assert vg[2, 3, 2] == -1
    assert vg.sum() == pytest.approx(1)
    # 25 us: halfway between bins 0 and 1
    vg2 = voxel_grid(ev_of([0], [0], [1], [BIG + 25]), W, H, 3, BIG, BIG + 100)
    assert vg2[0, 0, 0] == pytest.approx(0.5)
    assert vg2[1, 0, 0] == pytest.approx(0.5)
    est = est_grid(ev, W, H, 3, kernel="trilinear")
    np.testing.assert_allclose(est[0] - est[1], vg, atol=1e-6)


@settings(max_examples=80, deadline=None)
@given(
    n=st.integers(0, 40),
    burst=st.sampled_from([1, 100]),
    offset=st.sampled_from([0, BIG]),
    same_time=st.booleans(),
    seed=st.integers(0, 2**16),
)
@pytest.mark.slow
def test_extremes_finite_and_conserved(n: int, burst: int, offset: int, same_time: bool, seed: int) -> None:
    rng = np.random.default_rng(seed)
    t = np.full(n, offset + 7) if same_time else offset + np.sort(rng.integers(0, 1000, n))
    ev = ev_of(rng.integers(0, W, n), rng.integers(0, H, n), rng.choice([-1, 1], n), t)
    ev = EventArray.concatenate([ev] * burst)
    m = len(ev)
    reprs = all_reprs(ev)
    for r in reprs:
        assert np.isfinite(r).all()
    frame, counts, _, ts, vg, _, tri, _, _ = reprs
    assert counts.sum() == m
    assert frame.sum() == pytest.approx(float(ev.p.sum()))
    assert vg.sum() == pytest.approx(float(ev.p.sum()), abs=1e-3 * max(m, 1))
    assert tri.sum() == pytest.approx(m, rel=1e-4)
    assert ((ts >= 0) & (ts <= 1)).all()


def test_empty_and_window() -> None:
    for r in all_reprs(EventArray.empty()):
        assert np.isfinite(r).all()
        assert not r[r != -1].any()
    ev = ev_of([0, 1], [0, 0], [1, 1], [BIG, BIG + 10])
    assert count_image(ev, W, H, BIG + 5, BIG + 20).sum() == 1  # window excludes the first
    with pytest.raises(ValueError, match="before"):
        voxel_grid(ev, W, H, 3, 10, 5)
    with pytest.raises(ValueError, match="kernel"):
        est_grid(ev, W, H, 3, kernel="box")  # type: ignore[arg-type]


def test_large_offset_resolution() -> None:
    # 1 us apart, 2.8 h into the take: still resolved exactly.
    ev = ev_of([0, 0], [0, 0], [1, 1], [BIG, BIG + 1])
    vg = voxel_grid(ev, W, H, 2)
    assert vg[0, 0, 0] == 1
    assert vg[1, 0, 0] == 1


def _voxel_parity(ev: EventArray, bins: int, t0: int | None, t1: int | None, normalize: bool) -> None:
    raw, ref = voxel_grid(ev, W, H, bins, t0, t1), voxel_grid_bincount(ev, W, H, bins, t0, t1)
    assert raw.shape == (bins, H, W)
    if not normalize:
        assert_voxel_parity(raw, ref)
        return
    norm = voxel_grid(ev, W, H, bins, t0, t1, normalize=True)
    assert_voxel_parity(raw, ref, norm, voxel_grid_bincount(ev, W, H, bins, t0, t1, normalize=True))


@settings(max_examples=150, deadline=None)
@given(
    n=st.integers(0, 300),
    bins=st.sampled_from([1, 2, 3, 5, 9]),
    offset=st.sampled_from([0, BIG]),
    span=st.sampled_from([0, 1, 7, 1000, 50_000]),
    windowed=st.booleans(),
    normalize=st.booleans(),
    seed=st.integers(0, 2**16),
)
@pytest.mark.slow
def test_numba_voxel_grid_matches_the_bincount_reference(
    n: int, bins: int, offset: int, span: int, windowed: bool, normalize: bool, seed: int
) -> None:
    """Same bins, weights and normalisation as the numpy reference, events off the window and
    off the sensor included (both ignore them)."""
    rng = np.random.default_rng(seed)
    t = offset + np.sort(rng.integers(-5, span + 6, n))
    ev = ev_of(rng.integers(0, W + 2, n), rng.integers(0, H + 2, n), rng.choice([-1, 1], n), t)
    t0, t1 = (offset, offset + span) if windowed else (None, None)
    _voxel_parity(ev, bins, t0, t1, normalize)


@pytest.mark.parametrize("shape", [(5, H, W), (1, 1, 1), (2, 3, 17), (3, 20, 30)])
def test_reused_grid_is_cleared_bit_for_bit(shape: tuple[int, int, int]) -> None:
    """`out=` is cleared by testing blocks and rewriting the non-zero ones: whatever it
    held (sparse values, -0.0, NaN, a tail shorter than a block), the grid equals a new one bit
    for bit, +0.0 wherever no event landed."""
    bins, h, w = shape
    ev = ev_of([0, w - 1, 0], [0, h - 1, h - 1], [1, -1, 1], [BIG, BIG + 500, BIG + 999])
    rng = np.random.default_rng(0)
    for garbage in (0.0, -0.0, np.nan, 7.0):
        buf = np.zeros(shape, np.float32)
        flat = buf.reshape(-1)
        flat[rng.integers(0, flat.size, 3)] = garbage
        flat[-1] = garbage
        got = voxel_grid(ev, w, h, bins, BIG, BIG + 999, out=buf)
        want = voxel_grid(ev, w, h, bins, BIG, BIG + 999)
        np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))


def test_numba_voxel_grid_edge_cases() -> None:
    # Empty window: all zeros, normalised or not.
    for normalize in (False, True):
        _voxel_parity(EventArray.empty(), 5, BIG, BIG + 100, normalize)
        assert not voxel_grid(EventArray.empty(), W, H, 5, BIG, BIG + 100, normalize=normalize).any()
    # All events at one time, inside one bin; and a zero-length window (duration counts as 1 us).
    same = ev_of([0, 1, 1, 2], [0, 2, 2, 4], [1, -1, -1, 1], [BIG + 30] * 4)
    _voxel_parity(same, 5, BIG, BIG + 100, False)
    _voxel_parity(same, 5, None, None, True)
    vg = voxel_grid(same, W, H, 4)
    assert vg[0, 2, 1] == -2
    assert vg[1:].sum() == 0
    # Events on the window's last microsecond land whole in the last bin.
    last = ev_of([3, 3], [1, 1], [1, 1], [BIG, BIG + 999])
    vg = voxel_grid(last, W, H, 5, BIG, BIG + 999)
    assert vg[0, 1, 3] == 1
    assert vg[4, 1, 3] == 1
    assert vg.sum() == 2
    _voxel_parity(last, 5, BIG, BIG + 999, True)
    # Cancelling polarities leave an exact zero (not standardised) in both.
    cancel = ev_of([2, 2, 4], [2, 2, 0], [1, -1, 1], [BIG + 10, BIG + 10, BIG + 50])
    _voxel_parity(cancel, 3, BIG, BIG + 100, True)
    assert voxel_grid(cancel, W, H, 3, BIG, BIG + 100, normalize=True)[:, 2, 2].tolist() == [0, 0, 0]
    # A reused grid is zeroed first: the same values as a new one.
    buf = np.full((5, H, W), 7.0, np.float32)
    assert voxel_grid(last, W, H, 5, BIG, BIG + 999, out=buf) is buf
    np.testing.assert_array_equal(buf, voxel_grid(last, W, H, 5, BIG, BIG + 999))
    with pytest.raises(ValueError, match="out must be"):
        voxel_grid(last, W, H, 4, BIG, BIG + 999, out=buf)
    with pytest.raises(ValueError, match="bins"):
        voxel_grid(same, W, H, 0)
    with pytest.raises(ValueError, match="sensor size"):
        voxel_grid(same, 0, H, 3)


@settings(max_examples=40, deadline=None)
@given(
    sizes=st.lists(st.integers(0, 200), min_size=1, max_size=6),
    bins=st.sampled_from([1, 2, 5]),
    normalize=st.booleans(),
    seed=st.integers(0, 2**16),
)
@pytest.mark.slow
def test_voxel_gridder_equals_voxel_grid_window_after_window(
    sizes: list[int], bins: int, normalize: bool, seed: int
) -> None:
    """A reused buffer reset entry by entry gives each window's grid exactly, whatever came before."""
    rng = np.random.default_rng(seed)
    gridder = VoxelGridder(W, H, bins)
    for k, n in enumerate(sizes):
        t0 = BIG + k * 1000
        t = t0 + np.sort(rng.integers(-10, 1010, n))
        ev = ev_of(rng.integers(0, W + 1, n), rng.integers(0, H, n), rng.choice([-1, 1], n), t)
        got = gridder(ev, t0, t0 + 999, normalize=normalize)
        np.testing.assert_array_equal(got, voxel_grid(ev, W, H, bins, t0, t0 + 999, normalize=normalize))
        assert not got.flags.writeable
    with pytest.raises(ValueError, match="bins"):
        VoxelGridder(W, H, 0)
