"""Training-job reader: random time windows of a take as arrays, for a 4D trainer.

The layering rule keeps this package free of rigd.take, so the reader works on any object with
the `TakeLike` shape (rigd.take.reader.Take has it): `sensor(name)` giving one sensor's events
(`SensorLike`, as rigd.take's EventSeries: `events(t0, t1)`, `geometry`, `span`),
`camera(name)` (with `timestamps_us` and indexing giving an object with `.image` or an
array), and optionally `calibration` (a dict). Each sample holds the voxel grid of
the window, the camera frames inside it with their timestamps, the window bounds, and the
calibration when the take carries one.

Windows start uniformly at random, or (`sampling="events"`) with probability proportional to
the events they hold, as the 4D E-SloMo paper's event-weighted sampling does, so training sees
the fast, event-dense motion more often. The weights come from a coarse event histogram
(`sensor(name).histogram(bin_us)`, which `EventSeries` answers from the ms index), never from
the events themselves.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from reconstruction.representations import voxel_grid
from rigd.core.events import EventArray

log = logging.getLogger(__name__)


class SensorLike(Protocol):
    """One event sensor's events (rigd.take's EventSeries); `histogram(bin_us)` optional."""

    def events(self, t_start_us: int | None = None, t_end_us: int | None = None) -> EventArray: ...
    @property
    def geometry(self) -> tuple[int, int]: ...
    @property
    def span(self) -> tuple[int, int] | None: ...


class TakeLike(Protocol):
    def sensor(self, name: str) -> SensorLike: ...
    def camera(self, name: str) -> Any: ...


@dataclass
class Sample:
    t0_us: int
    t1_us: int
    voxels: NDArray[np.float32]
    frames: NDArray[Any]
    frame_times_us: NDArray[np.int64]
    calibration: dict[str, Any] | None = field(default=None)


def frame_array(item: Any) -> NDArray[Any]:
    return np.asarray(getattr(item, "image", item))


class WindowSampler:
    """Iterator over random windows of `window_us` of one event sensor (+ one camera if given).

    Random but reproducible (`seed`); `n_samples` windows, or endless with None. `sampling`:
    `"uniform"` start times, or `"events"`: a start's probability is proportional to the
    events in its window, counted in bins of `bin_us` (default: a tenth of the window, whole
    ms), so the weighting is exact to one bin. Needs `take.sensor(sensor).histogram`.
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
        sampling: Literal["uniform", "events"] = "uniform",
        bin_us: int | None = None,
    ) -> None:
        events = take.sensor(sensor)
        span = events.span
        if span is None or span[1] - span[0] < window_us:
            raise ValueError(f"sensor {sensor!r} has no event span of at least {window_us} us")
        if sampling not in ("uniform", "events"):
            raise ValueError(f"sampling must be 'uniform' or 'events', got {sampling!r}")
        self.take, self.sensor, self.camera = take, sensor, camera
        self.window_us, self.bins, self.n_samples = int(window_us), int(bins), n_samples
        self.span = (int(span[0]), int(span[1]))
        self.sampling = sampling
        self.width, self.height = events.geometry
        self._rng = np.random.default_rng(seed)
        self._weighted: tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]] | None = None
        if sampling == "events":
            self._weighted = self._event_weights(bin_us or max(1000, self.window_us // 10 // 1000 * 1000))

    def _event_weights(self, bin_us: int) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
        """Per histogram bin: the first and last start time in it that keeps the window inside
        the span, and the cumulative probability of drawing a start there (its window's events
        times the share of the bin that is a valid start)."""
        hist = getattr(self.take.sensor(self.sensor), "histogram", None)
        if hist is None:
            raise ValueError("sampling='events' needs a take whose sensor(name) has histogram(bin_us)")
        t0, counts = hist(int(bin_us))
        counts = np.asarray(counts, np.int64)
        k = np.arange(counts.size, dtype=np.int64)
        per_window = -(-self.window_us // bin_us)  # bins a window starting at a bin's start covers
        csum = np.concatenate([[0], np.cumsum(counts)])
        in_window = csum[np.minimum(k + per_window, counts.size)] - csum[k]
        lo = np.maximum(int(t0) + k * bin_us, self.span[0])
        hi = np.minimum(int(t0) + (k + 1) * bin_us - 1, self.span[1] - self.window_us)
        weight = np.where(hi >= lo, in_window * (hi - lo + 1) / bin_us, 0.0)
        if not weight.sum() > 0:
            raise ValueError(f"sensor {self.sensor!r}: no events to weigh windows by")
        cdf = np.cumsum(weight)
        return lo, hi, cdf / cdf[-1]

    def draw_starts(self, n: int, rng: np.random.Generator) -> NDArray[np.int64]:
        """`n` window start times (rig us) drawn as `sampling` says."""
        if self._weighted is None:
            return rng.integers(self.span[0], self.span[1] - self.window_us + 1, n)
        lo, hi, cdf = self._weighted
        k = np.minimum(np.searchsorted(cdf, rng.random(n), side="right"), cdf.size - 1)
        return lo[k] + rng.integers(0, hi[k] - lo[k] + 1)

    def sample_at(self, t0: int) -> Sample:
        t1 = t0 + self.window_us
        ev = self.take.sensor(self.sensor).events(t0, t1)
        vox = voxel_grid(ev, self.width, self.height, self.bins, t0, t1 - 1)
        frames: NDArray[Any] = np.zeros((0,), np.uint8)
        ftimes = np.zeros(0, np.int64)
        if self.camera is not None:
            series = self.take.camera(self.camera)
            ts = np.asarray(series.timestamps_us, np.int64)
            idx = np.nonzero((ts >= t0) & (ts < t1))[0]
            ftimes = ts[idx]
            if idx.size:
                frames = np.stack([frame_array(series[int(i)]) for i in idx])
        calib = getattr(self.take, "calibration", None)
        return Sample(t0, t1, vox, frames, ftimes, calib if isinstance(calib, dict) else None)

    def __iter__(self) -> Iterator[Sample]:
        k = 0
        while self.n_samples is None or k < self.n_samples:
            yield self.sample_at(int(self.draw_starts(1, self._rng)[0]))
            k += 1


def torch_dataset(
    sampler: WindowSampler, open_take: Callable[[], TakeLike] | None = None, **options: Any
) -> Any:
    """A torch dataset of the sampler's windows (`reconstruction.torch_dataset.WindowDataset`).

    `options` are `ReaderOptions` fields: `representation` ("voxel_grid", "event_frame",
    "time_surface"), `representation_on` ("worker": a dense grid from each worker, as before;
    "device": packed events from the workers, the grid built by `ds.to_device(batch, device)`),
    `bins`, `normalize`, `signed`, `tau_us`, `n_samples`, `seed`. `open_take`: how a worker
    opens its own take (e.g. `functools.partial(rigd.take.Take, path)`).
    """
    from reconstruction.torch_dataset import ReaderOptions, WindowDataset  # says how to install torch

    return WindowDataset(sampler, ReaderOptions(**options), open_take)
