"""WindowSampler on a duck-typed take."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

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

    def sensor(self, name: str) -> FakeTake:  # its one sensor's events are the take's
        return self

    def events(self, t_start_us: int | None = None, t_end_us: int | None = None) -> EventArray:
        t = self._ev.t
        return self._ev[(t >= (t_start_us or 0)) & (t < (t_end_us or 2**62))]

    @property
    def geometry(self) -> tuple[int, int]:
        return 6, 4

    @property
    def span(self) -> tuple[int, int] | None:
        return int(self._ev.t[0]), int(self._ev.t[-1])

    def camera(self, name: str) -> FakeSeries:
        return FakeSeries()


@pytest.mark.slow
def test_window_sampler() -> None:
    samples = list(WindowSampler(FakeTake(), "ev0", "cam0", window_us=100_000, bins=3, n_samples=4))
    assert len(samples) == 4
    for s in samples:
        assert s.voxels.shape == (3, 4, 6)
        assert np.isfinite(s.voxels).all()
        assert len(s.frames) == len(s.frame_times_us) >= 2
        assert ((s.frame_times_us >= s.t0_us) & (s.frame_times_us < s.t1_us)).all()
        assert s.calibration is not None


def test_torch_dataset_when_torch_is_installed() -> None:
    torch = pytest.importorskip("torch")
    from reconstruction.dataset import torch_dataset

    ds = torch_dataset(WindowSampler(FakeTake(), "ev0", "cam0", window_us=100_000, bins=3, n_samples=5))
    assert len(ds) == 5
    item = ds[0]
    assert isinstance(item["voxels"], torch.Tensor)
    assert tuple(item["voxels"].shape) == (3, 4, 6)
    assert torch.isfinite(item["voxels"]).all()
    loader = torch.utils.data.DataLoader(ds, batch_size=None, shuffle=False)
    assert sum(1 for _ in loader) == 5


def test_torch_losses_match_numpy_when_torch_is_installed() -> None:
    torch = pytest.importorskip("torch")
    from reconstruction import losses

    rng = np.random.default_rng(3)
    a = rng.uniform(0, 1, (32, 40))
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)
    tl = losses.torch_losses()
    ta, tb = torch.tensor(a), torch.tensor(b, requires_grad=True)
    assert float(tl.l1(tb, ta).detach()) == pytest.approx(losses.l1(b, a), rel=1e-6)
    s_t = tl.structure_ssim_loss(tb, ta)
    s_t.backward()  # differentiable, as a trainer needs
    assert tb.grad is not None
    assert torch.isfinite(tb.grad).all()
    assert float(s_t.detach()) == pytest.approx(losses.structure_ssim_loss(b, a), abs=0.02)
    stack = np.stack([a, b, a])
    assert float(tl.spatiotemporal_tv(torch.tensor(stack))) == pytest.approx(
        losses.spatiotemporal_tv(stack), rel=1e-3
    )
