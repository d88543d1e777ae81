"""The pixel model against analytic answers: counts, times, polarity, noise statistics."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_sim.event_model import EventSimulator, PixelModelConfig
from rigd.core.events import EventArray


def log_sim(width: int = 1, height: int = 1, **kw: object) -> EventSimulator:
    return EventSimulator(width, height, PixelModelConfig(input_kind="log", **kw))


def const(value: float, width: int = 1, height: int = 1) -> np.ndarray:
    return np.full((height, width), value, np.float32)


@pytest.mark.slow
@pytest.mark.parametrize("c", [0.3, 0.17])
@pytest.mark.parametrize("k", [1, 2, 3, 5, 8])
def test_ramp_of_k_thresholds_gives_k_events_at_the_right_times(k: int, c: float) -> None:
    sim = log_sim(threshold=c)
    t0, dt = 1_000, 10_000
    assert len(sim.step(const(1.0), t0)) == 0
    ev = sim.step(const(1.0 + k * c), t0 + dt)
    assert len(ev) == k
    assert (ev.p == 1).all()
    expected = t0 + np.arange(1, k + 1) * dt / k
    assert np.abs(ev.t - expected).max() <= 1


def test_ramp_over_several_steps_gives_the_same_times() -> None:
    """Sub-steps of a linear ramp change nothing: crossings are interpolated inside each step."""
    k, c, dt = 7, 0.3, 70_000
    one, many = log_sim(threshold=c), log_sim(threshold=c)
    one.step(const(0.0), 0)
    ev_one = one.step(const(k * c), dt)
    many.step(const(0.0), 0)
    parts = [many.step(const(k * c * j / 10), dt * j // 10) for j in range(1, 11)]
    ev_many = EventArray.concatenate(parts)
    assert len(ev_one) == len(ev_many) == k
    assert np.abs(ev_one.t - ev_many.t).max() <= 1
    assert np.abs(ev_one.t - np.arange(1, k + 1) * 10_000).max() <= 1


@pytest.mark.slow
def test_step_up_then_down_gives_on_then_off() -> None:
    sim = EventSimulator(8, 4)
    sim.step(np.full((4, 8), 40, np.uint8), 0)
    up = sim.step(np.full((4, 8), 200, np.uint8), 1_000)
    down = sim.step(np.full((4, 8), 40, np.uint8), 2_000)
    expect = int(np.log(201 / 41) / 0.3)
    assert len(up) == len(down) == 32 * expect
    assert (up.p == 1).all()
    assert (down.p == -1).all()
    assert up.t.max() <= 1_000 < down.t.min()


def test_on_off_symmetry() -> None:
    sim_up, sim_down = log_sim(threshold=0.25), log_sim(threshold=0.25)
    sim_up.step(const(0.0), 0)
    sim_down.step(const(1.0), 0)
    up = sim_up.step(const(1.0), 8_000)
    down = sim_down.step(const(0.0), 8_000)
    assert len(up) == len(down) == 4
    assert (up.p == 1).all()
    assert (down.p == -1).all()
    np.testing.assert_array_equal(up.t, down.t)


def test_separate_on_off_thresholds() -> None:
    sim = log_sim(threshold_on=0.2, threshold_off=0.4)
    sim.step(const(0.0), 0)
    up = sim.step(const(1.2), 1_000)
    down = sim.step(const(0.0), 2_000)
    assert (len(up), len(down)) == (6, 3)


def test_constant_input_gives_no_events() -> None:
    rng = np.random.default_rng(3)
    frame = rng.integers(0, 256, (32, 48)).astype(np.uint8)
    sim = EventSimulator(48, 32, PixelModelConfig(sigma=0.05, refractory_us=100, lowpass=True))
    sim.step(frame, 0)
    assert sum(len(sim.step(frame, 10_000 * i)) for i in range(1, 50)) == 0


def test_events_lie_inside_their_step_and_are_sorted() -> None:
    rng = np.random.default_rng(1)
    sim = EventSimulator(64, 64, PixelModelConfig(shot_noise_rate_hz=50.0, hot_pixel_fraction=0.01))
    sim.step(rng.integers(0, 256, (64, 64)).astype(np.uint8), 100)
    ev = sim.step(rng.integers(0, 256, (64, 64)).astype(np.uint8), 5_100)
    assert len(ev) > 1000
    assert ev.is_time_sorted()
    assert ev.t.min() > 100
    assert ev.t.max() <= 5_100
    assert len(np.unique(ev.t)) > 1000  # spread over the step, not stacked at the frame time


def test_mismatch_statistics_match_sigma() -> None:
    n, c, sigma = 100, 0.3, 0.03
    sim = log_sim(n, n, threshold=c, sigma=sigma, seed=11)
    assert sim.thr_on.mean() == pytest.approx(c, abs=0.002)
    assert sim.thr_on.std() == pytest.approx(sigma, rel=0.05)
    assert sim.thr_off.std() == pytest.approx(sigma, rel=0.05)
    assert abs(np.corrcoef(sim.thr_on.ravel(), sim.thr_off.ravel())[0, 1]) < 0.05
    # Recover each pixel's threshold from its events: a ramp of 30 log units over 10 s.
    span, dur = 30.0, 10_000_000
    sim.step(const(0.0, n, n), 0)
    ev = sim.step(const(span, n, n), dur)
    pix = ev.y.astype(np.int64) * n + ev.x
    counts = np.bincount(pix, minlength=n * n)
    first = np.full(n * n, np.iinfo(np.int64).max)
    last = np.zeros(n * n, np.int64)
    np.minimum.at(first, pix, ev.t)
    np.maximum.at(last, pix, ev.t)
    est = (last - first) / (counts - 1) * span / dur
    np.testing.assert_allclose(est, sim.thr_on.ravel(), atol=2e-4)
    assert est.std() == pytest.approx(sigma, rel=0.05)


def test_refractory_period_suppresses_events() -> None:
    # 40 crossings 100 us apart; a 450 us dead time keeps every 5th.
    sim = log_sim(threshold=0.1, refractory_us=450)
    sim.step(const(0.0), 0)
    ev = sim.step(const(4.0), 4_000)
    assert len(ev) == 8
    assert np.diff(ev.t).min() >= 450
    # The reference still advanced: no burst of held-back events afterwards.
    assert len(sim.step(const(4.0), 10_000)) == 0


def test_leak_rate_matches_configuration() -> None:
    n, rate, dur = 100, 2.0, 5_000_000
    sim = EventSimulator(n, n, PixelModelConfig(leak_rate_hz=rate, seed=4))
    frame = np.full((n, n), 128, np.uint8)
    sim.step(frame, 0)
    ev = EventArray.concatenate([sim.step(frame, dur * i // 50) for i in range(1, 51)])
    assert (ev.p == 1).all()
    assert len(ev) == pytest.approx(rate * n * n * dur * 1e-6, rel=0.02)
    # Random phase: events are spread over the time, not synchronized.
    hist = np.histogram(ev.t, bins=10, range=(0, dur))[0]
    assert hist.min() > 0.7 * hist.mean()


def test_shot_noise_rate_and_polarity() -> None:
    n, rate = 100, 20.0
    sim = EventSimulator(n, n, PixelModelConfig(shot_noise_rate_hz=rate, seed=2))
    frame = np.full((n, n), 128, np.uint8)
    sim.step(frame, 0)
    ev = EventArray.concatenate([sim.step(frame, 100_000 * i) for i in range(1, 11)])
    assert len(ev) == pytest.approx(rate * n * n, rel=0.05)
    assert (ev.p == 1).mean() == pytest.approx(0.5, abs=0.03)


def test_hot_pixels_fire() -> None:
    n = 100
    sim = EventSimulator(n, n, PixelModelConfig(hot_pixel_fraction=0.01, hot_pixel_rate_hz=200.0, seed=5))
    assert sim.hot_pixels.size == 100
    frame = np.full((n, n), 90, np.uint8)
    sim.step(frame, 0)
    ev = EventArray.concatenate([sim.step(frame, 50_000 * i) for i in range(1, 21)])
    pix = ev.y.astype(np.int64) * n + ev.x
    assert set(np.unique(pix)) <= set(sim.hot_pixels.tolist())
    assert len(ev) == pytest.approx(200.0 * 100, rel=0.05)


def test_lowpass_delays_response_more_in_the_dark() -> None:
    def first_event_time(level: int, lowpass: bool) -> int:
        sim = EventSimulator(1, 1, PixelModelConfig(lowpass=lowpass, lowpass_cutoff_hz=100.0))
        sim.step(np.full((1, 1), level, np.float32), 0)
        for i in range(1, 400):
            ev = sim.step(np.full((1, 1), level * 3, np.float32), i * 250)
            if len(ev):
                return int(ev.t[0])
        raise AssertionError("no event")

    assert first_event_time(60, False) <= 250
    bright, dark = first_event_time(80, True), first_event_time(25, True)
    assert 250 < bright < dark


def full_noise(seed: int) -> PixelModelConfig:
    return PixelModelConfig(
        sigma=0.03,
        refractory_us=50,
        leak_rate_hz=1.0,
        shot_noise_rate_hz=5.0,
        hot_pixel_fraction=0.001,
        seed=seed,
    )


def run_noisy(seed: int) -> EventArray:
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (6, 40, 60)).astype(np.uint8)
    sim = EventSimulator(60, 40, full_noise(seed))
    return EventArray.concatenate([sim.step(f, 20_000 * i) for i, f in enumerate(frames)])


def test_same_seed_same_events() -> None:
    a, b, c = run_noisy(7), run_noisy(7), run_noisy(8)
    for name in ("x", "y", "p", "t"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert len(a) != len(c) or not np.array_equal(a.t, c.t)


def test_all_zero_and_saturated_frames() -> None:
    sim = EventSimulator(16, 8)
    zero, sat = np.zeros((8, 16), np.uint8), np.full((8, 16), 255, np.uint8)
    sim.step(zero, 0)
    assert len(sim.step(zero, 1_000)) == 0
    up = sim.step(sat, 2_000)
    # lin-log: from the linear segment at 0 to log(256).
    assert len(up) > 0
    assert (up.p == 1).all()
    assert len(sim.step(sat, 3_000)) == 0
    down = sim.step(zero, 4_000)
    assert len(down) == len(up)
    assert (down.p == -1).all()


def test_uint16_input_matches_uint8_scaled() -> None:
    rng = np.random.default_rng(9)
    f8 = rng.integers(0, 256, (3, 20, 30)).astype(np.uint8)
    s8, s16 = EventSimulator(30, 20), EventSimulator(30, 20)
    e8 = EventArray.concatenate([s8.step(f, i * 1000 + 1) for i, f in enumerate(f8)])
    e16 = EventArray.concatenate(
        [s16.step(f.astype(np.uint16) * 257, i * 1000 + 1) for i, f in enumerate(f8)]
    )
    assert len(e8) > 100
    np.testing.assert_array_equal(e8.t, e16.t)
    np.testing.assert_array_equal(e8.p, e16.p)


def test_single_and_identical_frames() -> None:
    frame = np.random.default_rng(0).integers(0, 256, (10, 10)).astype(np.uint8)
    sim = EventSimulator(10, 10)
    assert len(sim.step(frame, 0)) == 0
    assert sim.initialized
    assert len(sim.step(frame.copy(), 1)) == 0


def test_megapixel_frame() -> None:
    w, h = 1280, 800
    rng = np.random.default_rng(0)
    base = rng.integers(20, 200, (h, w)).astype(np.uint8)
    sim = EventSimulator(w, h, PixelModelConfig(sigma=0.03))
    sim.step(base, 0)
    ev = sim.step(np.roll(base, 1, axis=1), 5_000)
    assert len(ev) > w * h // 2
    assert ev.is_time_sorted()
    assert int(ev.x.max()) == w - 1
    assert int(ev.y.max()) == h - 1


def test_clear_errors() -> None:
    sim = EventSimulator(10, 6)
    sim.step(np.zeros((6, 10), np.uint8), 0)
    with pytest.raises(ValueError, match=r"step 1 .*shape \(6, 11\)"):
        sim.step(np.zeros((6, 11), np.uint8), 10)
    with pytest.raises(ValueError, match="not after the previous"):
        sim.step(np.zeros((6, 10), np.uint8), 0)
    with pytest.raises(ValueError, match="NaN"):
        sim.step(np.full((6, 10), np.nan, np.float32), 20)


# The step runs three passes on numba's threads (firmware_sim.event_model, above
# `_emit_block`); they must give exactly the events of the serial reference kernel.


def _moving_frames(n: int, dtype: type = np.float32, w: int = 96, h: int = 70) -> list[np.ndarray]:
    rng = np.random.default_rng(12)
    tex: np.ndarray = rng.integers(0, 256, (h, w + 4 * n)).astype(dtype)
    if dtype == np.float32:
        tex += rng.uniform(0, 1, tex.shape).astype(np.float32)
    if dtype == np.uint16:
        tex *= 257
    return [tex[:, 4 * i : 4 * i + w].copy() for i in range(n)]


STEP_TIMES = [0, 33_333, 40_000, 40_001, 41_000, 100_000, 2_000_000]


def run_steps(cfg: PixelModelConfig, dtype: type = np.float32, **kw: object) -> list[EventArray]:
    frames = _moving_frames(len(STEP_TIMES), dtype)
    sim = EventSimulator(frames[0].shape[1], frames[0].shape[0], cfg, **kw)  # type: ignore[arg-type]
    return [sim.step(f, t) for f, t in zip(frames, STEP_TIMES, strict=True)]


def assert_same(a: list[EventArray], b: list[EventArray]) -> None:
    assert len(a) == len(b)
    for ea, eb in zip(a, b, strict=True):
        for name in ("x", "y", "p", "t"):
            xa, xb = getattr(ea, name), getattr(eb, name)
            assert xa.dtype == xb.dtype
            np.testing.assert_array_equal(xa, xb)


NOISY = [
    PixelModelConfig(threshold=0.2),
    PixelModelConfig(threshold=0.05, sigma=0.02),  # many events per pixel: the key buffer grows
    PixelModelConfig(
        threshold=0.15,
        sigma=0.03,
        lowpass=True,
        lowpass_cutoff_hz=80.0,
        refractory_us=300,
        leak_rate_hz=3.0,
        shot_noise_rate_hz=30.0,
        hot_pixel_fraction=0.01,
        seed=9,
    ),
]


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [np.float32, np.uint8, np.uint16])
@pytest.mark.parametrize("cfg", NOISY, ids=["clean", "dense", "noisy"])
def test_parallel_serial_and_reference_give_the_same_events(
    cfg: PixelModelConfig, dtype: type, monkeypatch: pytest.MonkeyPatch
) -> None:
    """uint8 frames go through a per-step table of levels and gains: still the same numbers."""
    import firmware_sim.event_model as em

    par = run_steps(cfg, dtype)
    ser = run_steps(cfg, dtype, parallel=False)
    assert sum(len(e) for e in par) > 1000
    assert all(e.is_time_sorted() for e in par)
    assert_same(par, ser)
    monkeypatch.setattr(em, "MAX_KEYED_SPAN", 1)  # every step through the serial reference kernel
    assert_same(par, run_steps(cfg, dtype))


def test_same_events_whatever_the_thread_count() -> None:
    import numba

    cfg = NOISY[2]
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = run_steps(cfg)
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]
        many = run_steps(cfg)
    finally:
        numba.set_num_threads(before)
    assert_same(one, many)
    assert_same(one, run_steps(cfg))


def test_simulators_in_threads_give_the_events_they_give_alone() -> None:
    from concurrent.futures import ThreadPoolExecutor

    cfg = NOISY[2]
    alone = run_steps(cfg)
    with ThreadPoolExecutor(3) as pool:
        results = list(pool.map(lambda _: run_steps(cfg), range(3)))
    for r in results:
        assert_same(alone, r)


def test_step_longer_than_the_event_keys_hold() -> None:
    """A step of ~20 min (past MAX_KEYED_SPAN) goes through the reference kernel, same rule."""
    sim = log_sim(threshold=0.25)
    dt = 1_200_000_000
    sim.step(const(0.0), 0)
    ev = sim.step(const(1.0), dt)
    assert len(ev) == 4
    assert np.abs(ev.t - np.arange(1, 5) * dt // 4).max() <= 1
