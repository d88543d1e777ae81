"""The torch side of the training reader: a map-style dataset of random windows whose
representation is built either in the data-loader workers or on the model's device.

`representation_on="worker"` (the old path) builds the dense grid in the worker and ships it:
18 MB a sample for a 5-bin voxel grid at 1280x720, which capped a 4-worker loader at 88
samples/s on a 16-core H100 machine (issue 24). `representation_on="device"` ships the window's
events packed (9 bytes an event, `reconstruction.packed_events`) and `to_device` builds the
grid where the model runs (`reconstruction.torch_representations`). Both give the training
loop the same batch:

    ds = torch_dataset(sampler, representation_on="device", open_take=partial(Take, path))
    loader = DataLoader(ds, batch_size=8, num_workers=4, collate_fn=ds.collate, pin_memory=True)
    for batch in loader:
        batch = ds.to_device(batch, "cuda")  # batch["voxels"]: (8, bins, H, W) float32 on the GPU

A worker should open its own take: `open_take` (a picklable callable, e.g.
`functools.partial(rigd.take.Take, path)`) is called once in each process that reads; without
it the sampler's take object is used, which a forked worker inherits and a spawned one cannot.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from reconstruction.dataset import TakeLike, WindowSampler, frame_array
from reconstruction.packed_events import PackedEvents, concat_packed, pack_events
from reconstruction.representations import event_frame, time_surface, voxel_grid

try:
    import torch

    from reconstruction.torch_representations import EventBatch
    from reconstruction.torch_representations import event_frame as torch_event_frame
    from reconstruction.torch_representations import time_surface as torch_time_surface
    from reconstruction.torch_representations import voxel_grid as torch_voxel_grid
except ImportError as exc:  # pragma: no cover - depends on the environment
    raise ImportError("the torch training reader needs PyTorch: pip install 'rigd[torch]'") from exc

log = logging.getLogger(__name__)

Representation = Literal["voxel_grid", "event_frame", "time_surface"]
#: The batch key each representation is delivered under ("voxels": the old dataset's name).
OUTPUT_KEY: dict[str, str] = {
    "voxel_grid": "voxels",
    "event_frame": "event_frame",
    "time_surface": "time_surface",
}


class ReaderOptions(BaseModel):
    """What the dataset delivers and where it is built."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    representation: Representation = "voxel_grid"
    representation_on: Literal["worker", "device"] = "worker"
    #: Voxel grid bins; None: the sampler's.
    bins: int | None = Field(default=None, ge=1)
    normalize: bool = False
    #: Event frame: sum of polarities (True) or 1 where any event fired.
    signed: bool = True
    tau_us: float = Field(default=10_000.0, gt=0)
    #: Windows in the dataset; None: the sampler's n_samples (1000 when it is endless).
    n_samples: int | None = Field(default=None, ge=1)
    #: Seed of the fixed window starts.
    seed: int = 0


class WindowDataset:
    """Item i is the window starting at a fixed random time (drawn once, as the sampler draws)."""

    def __init__(
        self,
        sampler: WindowSampler,
        options: ReaderOptions | None = None,
        open_take: Callable[[], TakeLike] | None = None,
    ) -> None:
        self.options = options or ReaderOptions()
        self.sensor, self.camera = sampler.sensor, sampler.camera
        self.width, self.height = sampler.width, sampler.height
        self.window_us = sampler.window_us
        self.bins = self.options.bins or sampler.bins
        n = self.options.n_samples or sampler.n_samples or 1000
        self.starts: NDArray[np.int64] = sampler.draw_starts(n, np.random.default_rng(self.options.seed))
        self._open_take = open_take
        self._take: TakeLike | None = sampler.take
        self._pid = os.getpid()
        self._frame_times: NDArray[np.int64] | None = None

    def __len__(self) -> int:
        return int(self.starts.shape[0])

    def __getstate__(self) -> dict[str, Any]:
        """What a spawned worker gets: everything but the open take, which it opens itself."""
        if self._open_take is None:
            raise TypeError(
                "WindowDataset without open_take cannot go to a spawned worker (an open take does not "
                "pickle): pass open_take=functools.partial(rigd.take.Take, path)"
            )
        state = dict(self.__dict__)
        state["_take"], state["_frame_times"], state["_pid"] = None, None, -1
        return state

    def take(self) -> TakeLike:
        """This process's take: opened with `open_take` once per process when given."""
        pid = os.getpid()
        if pid != self._pid or self._take is None:
            if self._open_take is not None:
                self._take, self._frame_times = self._open_take(), None
            elif self._take is None:
                raise RuntimeError("WindowDataset has neither a take nor open_take")
            self._pid = pid
        return self._take

    def _frames(self, take: TakeLike, t0: int, t1: int) -> tuple[NDArray[Any], NDArray[np.int64]]:
        """The camera's frames with t0 <= t < t1 (stacked) and their times."""
        if self.camera is None:
            return np.zeros((0,), np.uint8), np.zeros(0, np.int64)
        series = take.camera(self.camera)
        if self._frame_times is None:
            self._frame_times = np.asarray(series.timestamps_us, np.int64)
        ts = self._frame_times
        a, b = int(np.searchsorted(ts, t0, side="left")), int(np.searchsorted(ts, t1, side="left"))
        if b <= a:
            return np.zeros((0,), np.uint8), ts[a:a]
        return np.stack([frame_array(series[i]) for i in range(a, b)]), ts[a:b]

    def _dense(self, ev: Any, t0: int, t_last: int) -> NDArray[np.float32]:
        o, w, h = self.options, self.width, self.height
        if o.representation == "voxel_grid":
            return voxel_grid(ev, w, h, self.bins, t0, t_last, normalize=o.normalize)
        if o.representation == "event_frame":
            return event_frame(ev, w, h, t0, t_last, signed=o.signed)
        return time_surface(ev, w, h, t0, t_last, tau_us=o.tau_us)

    def __getitem__(self, i: int) -> dict[str, Any]:
        take = self.take()
        t0 = int(self.starts[i])
        t1 = t0 + self.window_us
        ev = take.sensor(self.sensor).events(t0, t1)
        frames, ftimes = self._frames(take, t0, t1)
        item: dict[str, Any] = {
            "frames": torch.from_numpy(np.ascontiguousarray(frames)),
            "frame_times_us": torch.from_numpy(ftimes),
            "t0_us": t0,
            "t1_us": t1,
        }
        if self.options.representation_on == "device":
            item["events"] = pack_events(ev, self.width, self.height, t0, t1 - 1)
        else:
            item[OUTPUT_KEY[self.options.representation]] = torch.from_numpy(self._dense(ev, t0, t1 - 1))
        return item

    def collate(self, items: Sequence[dict[str, Any]]) -> dict[str, Any]:
        """A batch: representations stacked (worker) or events concatenated (device); frames of
        all windows concatenated, `frame_counts` per window."""
        if not items:
            raise ValueError("a batch needs at least one item")
        frames = [it["frames"] for it in items]
        batch: dict[str, Any] = {
            "frames": torch.cat(frames) if any(f.numel() for f in frames) else frames[0],
            "frame_counts": torch.tensor([len(it["frame_times_us"]) for it in items], dtype=torch.int64),
            "frame_times_us": torch.cat([it["frame_times_us"] for it in items]),
            "t0_us": torch.tensor([it["t0_us"] for it in items], dtype=torch.int64),
            "t1_us": torch.tensor([it["t1_us"] for it in items], dtype=torch.int64),
        }
        if self.options.representation_on == "device":
            packed: list[PackedEvents] = [it["events"] for it in items]
            batch["events"] = EventBatch.from_packed(concat_packed(packed))
            batch["events_off_sensor"] = torch.tensor([p.off_sensor for p in packed], dtype=torch.int64)
        else:
            key = OUTPUT_KEY[self.options.representation]
            batch[key] = torch.stack([it[key] for it in items])
        return batch

    def to_device(
        self, batch: dict[str, Any], device: torch.device | str, non_blocking: bool = True
    ) -> dict[str, Any]:
        """The batch on `device`, its representation built there when it came as events."""
        out = {
            k: v.to(device, non_blocking=non_blocking) if isinstance(v, torch.Tensor | EventBatch) else v
            for k, v in batch.items()
        }
        events = out.get("events")
        if isinstance(events, EventBatch):
            out[OUTPUT_KEY[self.options.representation]] = self.represent(events)
        return out

    def represent(self, events: EventBatch) -> torch.Tensor:
        """The dataset's representation of a batch of windows, on the batch's device."""
        o = self.options
        if o.representation == "voxel_grid":
            return torch_voxel_grid(events, self.bins, normalize=o.normalize)
        if o.representation == "event_frame":
            return torch_event_frame(events, signed=o.signed)
        return torch_time_surface(events, tau_us=o.tau_us)
