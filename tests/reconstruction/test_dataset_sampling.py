"""Event-weighted window sampling (`WindowSampler(sampling="events")`) on a real take whose
activity sits in one half: most windows land there, uniform sampling splits them evenly.
Seeds are fixed, so the bounds are checks of one deterministic draw, not flaky statistics."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from reconstruction.dataset import WindowSampler, torch_dataset
from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.errors import TakeError
from rigd.core.events import EventArray
from rigd.core.schema import SyncReport
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.take import TakeWriter, open_take
from rigd.take.seal import finalize_take

W, H = 32, 24
T0, MID, T1 = 1_000_000, 1_500_000, 2_000_000
WINDOW = 50_000


def write_take(path: Path) -> None:
    """200k events in [T0, MID), 10k in [MID, T1): 20x the activity in the first half."""
    rng = np.random.default_rng(0)
    t = np.sort(np.concatenate([rng.integers(T0, MID, 200_000), rng.integers(MID, T1, 10_000)]))
    t[0], t[-1] = T0, T1 - 1
    n = t.size
    ev = EventArray.from_arrays(rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, 2, n), t)
    cfg = WriterConfig(event_chunk=4096, fsync=False)
    w = TakeWriter(path, rig_config_json="{}", take_id="sampling", config=cfg, rigd_version="t")
    w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="sim://t/ev0"), W, H, "{}")
    w.append_events("ev0", ev)
    first = T0 + 3_500  # events before it: negative stored t, histogram bins before t_offset
    w.append_pulses(PulseBatch(np.zeros(1, np.int64), np.array([first]), np.zeros(1, np.int64)))
    report = SyncReport(rate_hz=30.0, n_pulses=1, t_first_pulse_us=first, t_last_pulse_us=first)
    finalize_take(w, {"ev0": ClockMap.identity()}, {}, report)
    w.close()


@pytest.fixture(scope="module")
def take_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("sampling") / "take.h5"
    write_take(path)
    return path


def first_half_share(starts: np.ndarray) -> float:
    return float(np.mean(starts + WINDOW // 2 < MID))


@pytest.mark.slow
def test_event_weighted_windows_follow_activity(take_path: Path) -> None:
    with open_take(take_path) as take:
        ev = WindowSampler(take, "ev0", window_us=WINDOW, sampling="events", seed=3)
        uni = WindowSampler(take, "ev0", window_us=WINDOW, sampling="uniform", seed=3)
        s_ev = ev.draw_starts(2000, np.random.default_rng(5))
        s_uni = uni.draw_starts(2000, np.random.default_rng(5))
        # Expected: ~0.94 of the weight lies in windows centred in the first half.
        assert first_half_share(s_ev) > 0.85
        assert 0.4 < first_half_share(s_uni) < 0.6
        for drawn in (s_ev, s_uni):
            assert drawn.min() >= T0
            assert drawn.max() <= T1 - 1 - WINDOW
        # Iterating draws the same way, and each window holds what EventSeries.events says.
        samples = list(WindowSampler(take, "ev0", window_us=WINDOW, bins=2, n_samples=40, sampling="events"))
        assert first_half_share(np.array([s.t0_us for s in samples])) > 0.75
        s = samples[0]
        assert s.voxels.shape == (2, H, W)
        assert (np.abs(s.voxels).sum() > 0) == (len(take.sensor("ev0").events(s.t0_us, s.t1_us)) > 0)


def test_event_histogram_matches_the_events(take_path: Path) -> None:
    with open_take(take_path) as take:
        t = take.sensor("ev0").events().t
        for bin_us in (1000, 5000, 7000):
            start, counts = take.sensor("ev0").histogram(bin_us)
            edges = start + bin_us * np.arange(counts.size + 1)
            np.testing.assert_array_equal(counts, np.histogram(t, edges)[0])
            assert counts.sum() == t.size
        with pytest.raises(TakeError, match="multiple of 1000"):
            take.sensor("ev0").histogram(1500)


def test_event_sampling_needs_a_histogram() -> None:
    class NoHistogram:
        def sensor(self, name: str) -> NoHistogram:
            return self

        span = (0, 1_000_000)
        geometry = (W, H)

    with pytest.raises(ValueError, match="histogram"):
        WindowSampler(NoHistogram(), "ev0", sampling="events")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="sampling"):
        WindowSampler(NoHistogram(), "ev0", sampling="busy")  # type: ignore[arg-type]


@pytest.mark.slow
def test_torch_dataset_uses_the_sampling(take_path: Path) -> None:
    pytest.importorskip("torch")
    with open_take(take_path) as take:
        ds = torch_dataset(WindowSampler(take, "ev0", window_us=WINDOW, n_samples=200, sampling="events"))
        starts = np.array([ds[i]["t0_us"] for i in range(len(ds))])
        assert first_half_share(starts) > 0.8
