"""BAF: exact agreement with a literal brute-force reading of the rule, streaming, extremes."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from reconstruction import filters
from reconstruction.filters import BackgroundActivityFilter, background_activity_filter
from rigd.core.events import EventArray


def brute_force(
    ev: EventArray, radius: int, window: int, support: int, metric: str, update_on_drop: bool
) -> NDArray[np.bool_]:
    """O(n^2) reading of the definition in reconstruction.filters (test-only Python loop)."""
    x, y, p, t = (a.astype(np.int64) for a in (ev.x, ev.y, ev.p, ev.t))
    keep = np.zeros(len(ev), bool)
    for i in range(len(ev)):
        pixels = set()
        for k in range(i):
            if p[k] != p[i] or (x[k] == x[i] and y[k] == y[i]):
                continue
            if not update_on_drop and not keep[k]:
                continue
            dx, dy = abs(x[k] - x[i]), abs(y[k] - y[i])
            near = max(dx, dy) <= radius if metric == "chebyshev" else dx * dx + dy * dy <= radius**2
            if near and t[i] - t[k] <= window:
                pixels.add((x[k], y[k]))
        keep[i] = len(pixels) >= support
    return keep


@st.composite
def event_streams(draw: st.DrawFn) -> tuple[EventArray, int, int]:
    w = draw(st.integers(1, 12))
    h = draw(st.integers(1, 12))
    n = draw(st.integers(0, 120))
    x = draw(st.lists(st.integers(0, w - 1), min_size=n, max_size=n))
    y = draw(st.lists(st.integers(0, h - 1), min_size=n, max_size=n))
    p = draw(st.lists(st.sampled_from([-1, 1]), min_size=n, max_size=n))
    dt = draw(
        st.lists(
            st.integers(0, 25) | st.sampled_from([2**15 - 1, 2**15, 2**16, 2**30 - 1, 2**30, 5 * 10**9]),
            min_size=n,
            max_size=n,
        )
    )
    t0 = draw(st.sampled_from([0, 10_000_000_000]))
    t = t0 + np.cumsum(np.asarray(dt, np.int64))
    return EventArray.from_arrays(x, y, p, t), w, h


@settings(max_examples=150, deadline=None)
@given(
    data=event_streams(),
    radius=st.integers(1, 3),
    window=st.integers(0, 40) | st.sampled_from([32_767, 32_768, 70_000]),
    support=st.integers(0, 3),
    metric=st.sampled_from(["chebyshev", "euclidean"]),
    update_on_drop=st.booleans(),
)
@pytest.mark.slow
def test_matches_brute_force(
    data: tuple[EventArray, int, int],
    radius: int,
    window: int,
    support: int,
    metric: str,
    update_on_drop: bool,
) -> None:
    ev, w, h = data
    baf = BackgroundActivityFilter(
        w,
        h,
        radius_px=radius,
        window_us=window,
        min_support=support,
        metric=metric,  # type: ignore[arg-type]
        update_on_drop=update_on_drop,
    )
    got = baf.mask(ev)
    want = brute_force(ev, radius, window, support, metric, update_on_drop)
    np.testing.assert_array_equal(got, want)


@pytest.mark.slow
@settings(max_examples=60, deadline=None)
@given(data=event_streams(), cuts=st.lists(st.integers(0, 120), max_size=5))
def test_chunked_equals_whole(data: tuple[EventArray, int, int], cuts: list[int]) -> None:
    ev, w, h = data
    whole = BackgroundActivityFilter(w, h).mask(ev)
    baf = BackgroundActivityFilter(w, h)
    bounds = [0, *sorted(min(c, len(ev)) for c in cuts), len(ev)]
    parts = [baf.mask(ev[a:b]) for a, b in itertools.pairwise(bounds)]
    np.testing.assert_array_equal(np.concatenate(parts) if parts else np.zeros(0, bool), whole)


def test_paper_defaults_keep_edges_drop_isolated() -> None:
    # A vertical edge sweeping right, one column per 5 us: events after the first columns have support.
    cols = np.repeat(np.arange(20), 10)
    rows = np.tile(np.arange(10), 20)
    t = cols * 5
    edge = EventArray.from_arrays(cols, rows, np.ones_like(cols), t)
    kept = background_activity_filter(edge, 64, 64)
    assert len(kept) >= 0.9 * len(edge)
    # Isolated noise: far apart in space or time.
    rng = np.random.default_rng(0)
    n = 500
    noise = EventArray.from_arrays(
        rng.integers(0, 640, n), rng.integers(0, 480, n), rng.choice([-1, 1], n), np.arange(n) * 1000
    )
    assert len(background_activity_filter(noise, 640, 480)) == 0


def test_extremes() -> None:
    baf = BackgroundActivityFilter(8, 8)
    assert len(baf.filter(EventArray.empty())) == 0
    single = EventArray.from_arrays([3], [3], [1], [10**10])
    assert len(baf.filter(single)) == 0
    # all at one timestamp, a 100x burst on a 3x3 block: everything after the first pixels is supported
    xs, ys = np.meshgrid(np.arange(3), np.arange(3))
    burst = EventArray.from_arrays(
        np.tile(xs.ravel(), 100), np.tile(ys.ravel(), 100), np.ones(900, int), np.full(900, 10**10 + 5)
    )
    m = baf.mask(burst)
    assert m[9:].all()
    assert not m[0]
    with pytest.raises(ValueError, match="previous chunk"):
        baf.mask(EventArray.from_arrays([0], [0], [1], [0]))
    with pytest.raises(ValueError, match="sorted"):
        BackgroundActivityFilter(8, 8).mask(EventArray.from_arrays([0, 0], [0, 0], [1, 1], [5, 1]))
    with pytest.raises(ValueError, match="outside"):
        BackgroundActivityFilter(8, 8).mask(EventArray.from_arrays([8], [0], [1], [5]))


@pytest.mark.slow
@pytest.mark.parametrize(("radius", "metric"), [(4, "chebyshev"), (5, "euclidean"), (40, "euclidean")])
def test_large_radius_matches_brute_force(radius: int, metric: str) -> None:
    # radius 40: rows of 81 px take two SIMD compares (64 + 24 lanes) in the kernel
    rng = np.random.default_rng(radius)
    n, w, h = 400, 3 * radius, 2 * radius + 3
    t = np.cumsum(rng.integers(0, 4, n))
    ev = EventArray.from_arrays(rng.integers(0, w, n), rng.integers(0, h, n), rng.choice([-1, 1], n), t)
    window = 30
    for support, update_on_drop in [(2, True), (6, True), (1, False)]:
        got = BackgroundActivityFilter(
            w,
            h,
            radius_px=radius,
            window_us=window,
            min_support=support,
            metric=metric,  # type: ignore[arg-type]
            update_on_drop=update_on_drop,
        ).mask(ev)
        want = brute_force(ev, radius, window, support, metric, update_on_drop)
        if update_on_drop:  # update_on_drop=False with support >= 1 never bootstraps: nothing kept
            assert 0 < got.sum() < n
        np.testing.assert_array_equal(got, want)


@pytest.mark.slow
@pytest.mark.parametrize("window", [32_766, 32_767, 32_768, 1_000_000])
@pytest.mark.parametrize("block", [filters.BLOCK_EVENTS, 7])
@pytest.mark.parametrize("threads", [1, 2])
def test_map_types_and_rebase_match_brute_force(
    window: int, block: int, threads: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    # windows up to 32767 us keep int16 times (rebased every ~65 ms of stream), longer ones int32;
    # gaps around the int16 range and the window exercise the rebase and its saturation; blocks of
    # 7 events put the kernel's block edges (and rebases) everywhere in the stream; with two
    # threads each polarity's kernel rebases its own plane where the whole stream does
    monkeypatch.setattr(filters, "BLOCK_EVENTS", block)
    monkeypatch.setattr(filters, "SPLIT_MIN_EVENTS", 0)
    monkeypatch.setattr(filters, "SPLIT_MAX_SHARE", 1.0)
    rng = np.random.default_rng(window)
    n, w, h = 600, 9, 7
    gaps = rng.choice([0, 1, 3, window // 2, window - 1, window, window + 1, 2**15, 2**16, 2**31], n)
    t = 7 + np.cumsum(gaps)
    ev = EventArray.from_arrays(rng.integers(0, w, n), rng.integers(0, h, n), rng.choice([-1, 1], n), t)
    for support in (1, 2):
        got = BackgroundActivityFilter(w, h, window_us=window, min_support=support, threads=threads).mask(ev)
        want = brute_force(ev, 3, window, support, "chebyshev", True)
        assert 0 < got.sum() < n
        np.testing.assert_array_equal(got, want)


@pytest.mark.slow
@settings(max_examples=60, deadline=None)
@given(data=event_streams(), cuts=st.lists(st.integers(0, 120), max_size=5), in_kernel=st.booleans())
def test_filter_lists_exactly_the_masked_events(
    data: tuple[EventArray, int, int], cuts: list[int], in_kernel: bool
) -> None:
    # filter() has the scan list the kept indices; it must give events[mask] chunk by chunk, with
    # the input checked in its own pass or inside the kernel
    ev, w, h = data
    whole = BackgroundActivityFilter(w, h).mask(ev)
    baf = BackgroundActivityFilter(w, h)
    if in_kernel:
        baf_check = filters.CHECK_BYTES_PER_EVENT
        filters.CHECK_BYTES_PER_EVENT = 1 << 40
    try:
        bounds = [0, *sorted(min(c, len(ev)) for c in cuts), len(ev)]
        parts = [baf.filter(ev[a:b]) for a, b in itertools.pairwise(bounds)]
    finally:
        if in_kernel:
            filters.CHECK_BYTES_PER_EVENT = baf_check
    got = EventArray.concatenate(parts)
    want = ev[whole]
    for name in ("x", "y", "p", "t"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
        assert getattr(got, name).dtype == getattr(ev, name).dtype


def _burst(rng: np.random.Generator, n: int, w: int, h: int, t0: int) -> EventArray:
    t = t0 + np.cumsum(rng.integers(0, 3, n))
    return EventArray.from_arrays(rng.integers(0, w, n), rng.integers(0, h, n), rng.choice([-1, 1], n), t)


@pytest.mark.slow
@settings(max_examples=80, deadline=None)
@given(
    data=event_streams(),
    cuts=st.lists(st.integers(0, 120), max_size=5),
    radius=st.integers(1, 3),
    window=st.integers(0, 40) | st.sampled_from([32_767, 32_768, 70_000]),
    support=st.integers(0, 3),
    update_on_drop=st.booleans(),
    in_kernel=st.booleans(),
)
def test_two_threads_keep_what_one_keeps(
    data: tuple[EventArray, int, int],
    cuts: list[int],
    radius: int,
    window: int,
    support: int,
    update_on_drop: bool,
    in_kernel: bool,
) -> None:
    # threads=2 filters each polarity on its own thread against its own plane of the map; chunk by
    # chunk, mask() and filter() must give exactly what one thread gives (which the brute force
    # checks above), and leave the same state behind for the next chunk
    ev, w, h = data
    kw = {"radius_px": radius, "window_us": window, "min_support": support, "update_on_drop": update_on_drop}
    one, two = BackgroundActivityFilter(w, h, **kw), BackgroundActivityFilter(w, h, threads=2, **kw)  # type: ignore[arg-type]
    saved = filters.SPLIT_MIN_EVENTS, filters.SPLIT_MAX_SHARE, filters.CHECK_BYTES_PER_EVENT
    filters.SPLIT_MIN_EVENTS, filters.SPLIT_MAX_SHARE = 0, 1.0
    if in_kernel:
        filters.CHECK_BYTES_PER_EVENT = 1 << 40
    try:
        bounds = [0, *sorted(min(c, len(ev)) for c in cuts), len(ev)]
        for k, (a, b) in enumerate(itertools.pairwise(bounds)):
            if k % 2:
                np.testing.assert_array_equal(two.mask(ev[a:b]), one.mask(ev[a:b]))
            else:
                got, want = two.filter(ev[a:b]), one.filter(ev[a:b])
                for name in ("x", "y", "p", "t"):
                    np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
                    assert getattr(got, name).dtype == getattr(ev, name).dtype
    finally:
        filters.SPLIT_MIN_EVENTS, filters.SPLIT_MAX_SHARE, filters.CHECK_BYTES_PER_EVENT = saved
    assert (two.n_in, two.n_kept) == (one.n_in, one.n_kept)
    np.testing.assert_array_equal(two._last, one._last)


def test_threads_is_one_or_two() -> None:
    with pytest.raises(ValueError, match="threads must be 1 or 2"):
        BackgroundActivityFilter(8, 8, threads=3)


def test_two_threads_split_only_large_chunks_with_both_polarities(monkeypatch: pytest.MonkeyPatch) -> None:
    # the split pays for its merge only on a large chunk whose polarities are near half and half;
    # otherwise the chunk runs on one thread (same result either way)
    rng = np.random.default_rng(3)
    n = filters.SPLIT_MIN_EVENTS
    balanced = _burst(rng, n, 64, 64, 0)
    skewed = EventArray(
        balanced.x, balanced.y, np.where(rng.random(n) < 0.7, 1, -1).astype(np.int8), balanced.t
    )
    baf = BackgroundActivityFilter(64, 64, threads=2)
    calls: list[int] = []
    split = baf._run_split
    monkeypatch.setattr(baf, "_run_split", lambda ev: calls.append(len(ev)) or split(ev))
    for ev, splits in ((balanced, True), (skewed, False), (balanced[: n - 1], False)):
        calls.clear()
        one = BackgroundActivityFilter(64, 64).mask(ev)
        baf.reset()
        np.testing.assert_array_equal(baf.mask(ev), one)
        assert bool(calls) == splits


@pytest.mark.parametrize("fault", ["place", "order"])
@pytest.mark.parametrize("method", ["mask", "filter"])
@pytest.mark.parametrize("threads", [1, 2])
def test_a_bad_event_deep_in_a_large_chunk_names_itself_and_changes_nothing(
    fault: str, method: str, threads: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    # 40 000 events on a 64x64 sensor: far more bytes than the map, so the kernel checks them block by
    # block; the bad event sits in the seventh block, after six blocks were already filtered. A 20 ms
    # window reaches back from `after` into those blocks, so what they left in the map would change
    # what comes after.
    rng = np.random.default_rng(5)
    w, h = 64, 64

    monkeypatch.setattr(filters, "SPLIT_MIN_EVENTS", 1000)
    monkeypatch.setattr(filters, "SPLIT_MAX_SHARE", 1.0)

    def make() -> BackgroundActivityFilter:
        return BackgroundActivityFilter(w, h, window_us=20_000, threads=threads)

    history = _burst(rng, 5_000, w, h, 0)
    bad = _burst(rng, 40_000, w, h, int(history.t[-1]))
    assert len(bad) * filters.CHECK_BYTES_PER_EVENT > 2 * make()._last.nbytes
    at = 6 * filters.BLOCK_EVENTS + 123
    if fault == "place":
        bad.x[at] = w
        match = f"event {at} at \\(x=64, y={int(bad.y[at])}\\) is outside the 64x64 sensor"
    else:
        bad.t[at] = bad.t[at - 1] - 1
        match = f"event {at} \\({int(bad.t[at])} us\\) comes before event {at - 1}"
    after = _burst(rng, 20_000, w, h, int(bad.t[-1]) + 1)

    baf = make()
    getattr(baf, method)(history)
    with pytest.raises(ValueError, match=match):
        getattr(baf, method)(bad)
    got = baf.mask(after)
    clean = make()
    clean.mask(history)
    np.testing.assert_array_equal(got, clean.mask(after))
    assert baf.n_in == clean.n_in
    assert baf.n_kept == clean.n_kept
