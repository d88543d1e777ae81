"""WindowSampler on a duck-typed take."""

from __future__ import annotations

from typing import Any

import numpy as np

from reconstruction.dataset import WindowSampler
from rigd.core.events import EventArray


class FakeSeries:
    timestamps_us = np.arange(0, 1_000_000, 33_333, dtype=np.int64)

    def __getitem__(self, i: int) -> Any:
        return np.full((4, 6), i, np.uint8)


class FakeTake:
    def __init__(self) -> None:
        self.calibration = {"K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}
        n = 10_000
        rng = np.random.default_rng(0)
        self._ev = EventArray.from_arrays(
            rng.integers(0, 6, n),
            rng.integers(0, 4, n),
            rng.choice([-1, 1], n),
            np.sort(rng.integers(0, 10**6, n)),
        )

    def events(self, sensor: str, t_start_us: int | None = None, t_end_us: int | None = None) -> EventArray:
        t = self._ev.t
        return self._ev[(t >= (t_start_us or 0)) & (t < (t_end_us or 2**62))]

    def geometry(self, sensor: str) -> tuple[int, int]:
        return 6, 4

    def event_span(self, sensor: str) -> tuple[int, int] | None:
        return int(self._ev.t[0]), int(self._ev.t[-1])

    def frames(self, camera: str) -> FakeSeries:
        return FakeSeries()


def test_window_sampler() -> None:
    samples = list(WindowSampler(FakeTake(), "ev0", "cam0", window_us=100_000, bins=3, n_samples=4))
    assert len(samples) == 4
    for s in samples:
        assert s.voxels.shape == (3, 4, 6)
        assert np.isfinite(s.voxels).all()
        assert len(s.frames) == len(s.frame_times_us) >= 2
        assert ((s.frame_times_us >= s.t0_us) & (s.frame_times_us < s.t1_us)).all()
        assert s.calibration is not None
