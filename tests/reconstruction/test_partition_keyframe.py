"""Canonical keyframe (paper Eq. 3): the O(n log n) selection equals the brute-force argmin."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from reconstruction.partition import (
    _accumulated_maps,
    canonical_keyframe,
    canonical_keyframe_bruteforce,
)
from rigd.core.events import EventArray


def shapes(max_n: int = 40) -> st.SearchStrategy[tuple[int, int, int]]:
    return st.tuples(st.integers(1, max_n), st.integers(1, 4), st.integers(1, 4))


def check(maps: np.ndarray) -> None:
    """The sort path (forced even for a few maps) and the default dispatch both equal the reference."""
    ref = canonical_keyframe_bruteforce(maps)
    assert canonical_keyframe(maps, small_n=0) == ref
    assert canonical_keyframe(maps) == ref


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(hnp.arrays(np.float32, shapes(), elements=st.integers(-3, 3).map(float)))
def test_small_integer_maps_many_ties(maps: np.ndarray) -> None:
    check(maps)


@settings(max_examples=300, deadline=None)
@given(
    hnp.arrays(
        np.float32,
        shapes(),
        elements=st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False, width=32),
    )
)
@pytest.mark.slow
def test_float_maps(maps: np.ndarray) -> None:
    check(maps)


@settings(max_examples=200, deadline=None)
@given(
    hnp.arrays(
        np.float32,
        shapes(),
        elements=st.sampled_from([0.0, 1e-30, -1e-30, 0.1, 1e30, -1e30, 3e38, -3e38, 16777217.0]),
    )
)
@pytest.mark.slow
def test_extreme_magnitudes(maps: np.ndarray) -> None:
    check(maps)


@pytest.mark.slow
@settings(max_examples=100, deadline=None)
@given(st.data(), shapes(20), st.integers(2, 4))
def test_duplicated_maps(data: st.DataObject, shape: tuple[int, int, int], copies: int) -> None:
    """Repeated maps tie exactly: the lowest index wins in both."""
    base = data.draw(hnp.arrays(np.float32, shape, elements=st.floats(-100, 100, width=32)))
    idx = data.draw(st.permutations(list(np.repeat(np.arange(shape[0]), copies))))
    check(base[np.asarray(idx)])


@pytest.mark.parametrize("n", [1, 2, 3, 4, 7])
@pytest.mark.parametrize("value", [0.0, 1.0, -2.5, 1e30])
def test_constant_input(n: int, value: float) -> None:
    maps = np.full((n, 3, 2), value, np.float32)
    check(maps)
    assert canonical_keyframe_bruteforce(maps) == 0


def test_one_and_two_maps() -> None:
    rng = np.random.default_rng(1)
    for n in (1, 2):
        maps = rng.standard_normal((n, 5, 4)).astype(np.float32)
        check(maps)
    assert canonical_keyframe_bruteforce(maps) == 0


def test_symmetric_tie_takes_first() -> None:
    maps = np.array([0, 1, 2, 3], np.float32).reshape(4, 1, 1)  # V = 6, 4, 4, 6
    check(maps)
    assert canonical_keyframe_bruteforce(maps) == 1


@pytest.mark.parametrize("n", [3, 10, 50, 200, 600])
def test_random_sizes(n: int) -> None:
    rng = np.random.default_rng(n)
    walk = np.cumsum(rng.integers(-1, 2, (n, 12, 16)), axis=0).astype(np.float32)
    check(walk)
    check(rng.standard_normal((n, 6, 5)).astype(np.float32))
    check(rng.integers(0, 2, (n, 3, 3)).astype(np.float32))  # heavy ties


def test_large_integer_values_beyond_float64_exactness() -> None:
    """Sums above 2^53: the float path with its re-check still agrees."""
    rng = np.random.default_rng(7)
    maps = (rng.integers(-(2**20), 2**20, (40, 4, 4)) * 2.0**40).astype(np.float32)
    check(maps)


def test_accumulated_event_maps() -> None:
    """The maps `partition` builds (signed event counts) from a random stream."""
    rng = np.random.default_rng(3)
    n_ev, w, h = 20_000, 64, 48
    t = np.sort(rng.integers(0, 100_000, n_ev))
    ev = EventArray.from_arrays(
        rng.integers(0, w, n_ev), rng.integers(0, h, n_ev), rng.choice([-1, 1], n_ev), t
    )
    taus = np.arange(1_000, 100_001, 1_000, dtype=np.int64)
    check(_accumulated_maps(ev, w, h, 0, taus, 0.25))


def test_non_finite_rejected() -> None:
    maps = np.zeros((3, 2, 2), np.float32)
    maps[1, 0, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        canonical_keyframe(maps, small_n=0)


@pytest.mark.slow
def test_user_scale_runs() -> None:
    """100k maps (a long segment's candidate times) at a small map size: just runs."""
    rng = np.random.default_rng(0)
    maps = np.cumsum(rng.integers(-1, 2, (100_000, 8, 8), dtype=np.int8), axis=0, dtype=np.int32)
    k = canonical_keyframe(maps.astype(np.float32))
    assert 0 <= k < 100_000


@pytest.mark.slow
@settings(max_examples=200, deadline=None)
@given(hnp.arrays(np.int32, shapes(), elements=st.integers(-50, 50)))
def test_integer_maps_in_place_equal_the_reference(maps: np.ndarray) -> None:
    """int32 event-count maps (what `rigd reconstruct` builds) take the exact integer path, copied or
    shifted in place, and choose what the float64 reference chooses."""
    ref = canonical_keyframe_bruteforce(maps.astype(np.float64))
    assert canonical_keyframe(maps, small_n=0) == ref
    scratch = maps.copy()
    assert canonical_keyframe(scratch, small_n=0, overwrite=True) == ref
