"""Representations: exact values on small cases and the extremes of the issue."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from reconstruction.representations import (
    count_image,
    est_grid,
    event_frame,
    surface_of_active_events,
    time_surface,
    voxel_grid,
)
from rigd.core.events import EventArray

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
