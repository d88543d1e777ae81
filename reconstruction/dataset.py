"""Training-job reader: random time windows of a take as arrays, for a 4D trainer.

The layering rule keeps this package free of rigd.take, so the reader works on any object with
the `TakeLike` shape (rigd.take.reader.Take has it): `events(sensor, t0, t1)`, `geometry(sensor)`,
`event_span(sensor)`, `frames(camera)` (with `timestamps_us` and indexing giving an object with
`.image` or an array), and optionally `calibration` (a dict). Each sample holds the voxel grid of
the window, the camera frames inside it with their timestamps, the window bounds, and the
calibration when the take carries one.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from reconstruction.representations import voxel_grid
from rigd.core.events import EventArray

log = logging.getLogger(__name__)


class TakeLike(Protocol):
    def events(
        self, sensor: str, t_start_us: int | None = None, t_end_us: int | None = None
    ) -> EventArray: ...
    def geometry(self, sensor: str) -> tuple[int, int]: ...
    def event_span(self, sensor: str) -> tuple[int, int] | None: ...
    def frames(self, camera: str) -> Any: ...


@dataclass
class Sample:
    t0_us: int
    t1_us: int
    voxels: NDArray[np.float32]
    frames: NDArray[Any]
    frame_times_us: NDArray[np.int64]
    calibration: dict[str, Any] | None = field(default=None)


def _frame_array(item: Any) -> NDArray[Any]:
    return np.asarray(getattr(item, "image", item))


class WindowSampler:
    """Iterator over random windows of `window_us` of one event sensor (+ one camera if given).

    Random but reproducible (`seed`); `n_samples` windows, or endless with None.
    """

    def __init__(
        self,
        take: TakeLike,
        sensor: str,
        camera: str | None = None,
        *,
        window_us: int = 50_000,
        bins: int = 5,
        n_samples: int | None = 100,
        seed: int = 0,
    ) -> None:
        span = take.event_span(sensor)
        if span is None or span[1] - span[0] < window_us:
            raise ValueError(f"sensor {sensor!r} has no event span of at least {window_us} us")
        self.take, self.sensor, self.camera = take, sensor, camera
        self.window_us, self.bins, self.n_samples = int(window_us), int(bins), n_samples
        self.span = (int(span[0]), int(span[1]))
        self.width, self.height = take.geometry(sensor)
        self._rng = np.random.default_rng(seed)

    def sample_at(self, t0: int) -> Sample:
        t1 = t0 + self.window_us
        ev = self.take.events(self.sensor, t0, t1)
        vox = voxel_grid(ev, self.width, self.height, self.bins, t0, t1 - 1)
        frames: NDArray[Any] = np.zeros((0,), np.uint8)
        ftimes = np.zeros(0, np.int64)
        if self.camera is not None:
            series = self.take.frames(self.camera)
            ts = np.asarray(series.timestamps_us, np.int64)
            idx = np.nonzero((ts >= t0) & (ts < t1))[0]
            ftimes = ts[idx]
            if idx.size:
                frames = np.stack([_frame_array(series[int(i)]) for i in idx])
        calib = getattr(self.take, "calibration", None)
        return Sample(t0, t1, vox, frames, ftimes, calib if isinstance(calib, dict) else None)

    def __iter__(self) -> Iterator[Sample]:
        k = 0
        while self.n_samples is None or k < self.n_samples:
            t0 = int(self._rng.integers(self.span[0], self.span[1] - self.window_us + 1))
            yield self.sample_at(t0)
            k += 1


def torch_dataset(sampler: WindowSampler) -> Any:
    """A torch `Dataset` whose item i is the window starting at a fixed random time (seeded)."""
    try:
        import torch
        from torch.utils.data import Dataset
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("torch_dataset needs PyTorch: pip install 'rigd[torch]'") from exc
    n = sampler.n_samples or 1000
    rng = np.random.default_rng(0)
    starts = rng.integers(sampler.span[0], sampler.span[1] - sampler.window_us + 1, n)

    class _WindowDataset(Dataset):
        def __len__(self) -> int:
            return n

        def __getitem__(self, i: int) -> dict[str, Any]:
            s = sampler.sample_at(int(starts[i]))
            return {
                "voxels": torch.from_numpy(s.voxels),
                "frames": torch.from_numpy(np.ascontiguousarray(s.frames)),
                "frame_times_us": torch.from_numpy(s.frame_times_us),
                "t0_us": s.t0_us,
                "t1_us": s.t1_us,
            }

    return _WindowDataset()
