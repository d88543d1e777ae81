"""Voxel grids, event frames and time surfaces of a batch of windows, built in torch on the
device the model runs on (CUDA when there, the CPU otherwise).

Data-loader workers ship packed events (`reconstruction.packed_events`, 9 bytes an event); the
dense float grids are made here, after the batch is on the device, instead of in the workers
where they cost 18 MB of IPC a sample (issue 24). The conventions are those of
`reconstruction.representations`, and the tests hold the two to float32 tolerance:

* a window is [t0, t1], both inclusive; its duration is max(t1 - t0, 1) us;
* voxel grid: event time normalised as float64 of the integer time since t0, divided by the
  duration, times B - 1; its polarity split between the floor bin and the next (clamped to the
  last bin), bilinear; one bin takes every event whole; `normalize` standardises the non-zero
  entries of each window (population std, 1 where it is 0);
* event frame: per-pixel sum of polarities, or 1 where any event fired (`signed=False`);
* time surface: (2, H, W), channel 0 ON, 1 OFF: exp(-(t_ref - t_last) / tau), 0 where none,
  t_ref the window end unless given.

Scatter-adds are `index_add_` into float32 (atomic on CUDA, so sums may differ from run to run
in their last bits); the per-pixel latest time is `scatter_reduce_("amax")` in float64.
Importing this module needs torch: `pip install 'rigd[torch]'`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from reconstruction.packed_events import PackedBatch

try:
    import torch
except ImportError as exc:  # pragma: no cover - depends on the environment
    raise ImportError(
        "reconstruction.torch_representations needs PyTorch: pip install 'rigd[torch]'"
    ) from exc

if TYPE_CHECKING:  # a type mypy knows with or without torch installed
    from torch import Tensor
else:
    Tensor = torch.Tensor


@dataclass(frozen=True)
class EventBatch:
    """A batch of packed windows as torch tensors (on one device): `pix` int32, `p` int8,
    `dt` int32 per event; `counts`, `t0_us`, `t1_us` (inclusive) int64 per window."""

    pix: Tensor
    p: Tensor
    dt: Tensor
    counts: Tensor
    t0_us: Tensor
    t1_us: Tensor
    width: int
    height: int

    @classmethod
    def from_packed(cls, batch: PackedBatch) -> EventBatch:
        """Wraps the batch's arrays without copying (CPU tensors; `.to(device)` moves them)."""
        return cls(
            torch.from_numpy(batch.pix),
            torch.from_numpy(batch.p),
            torch.from_numpy(batch.dt),
            torch.from_numpy(batch.counts),
            torch.from_numpy(batch.t0_us),
            torch.from_numpy(batch.t1_us),
            batch.width,
            batch.height,
        )

    @property
    def size(self) -> int:
        return int(self.counts.shape[0])

    @property
    def device(self) -> torch.device:
        return self.pix.device

    def to(self, device: torch.device | str, non_blocking: bool = False) -> EventBatch:
        def move(t: Tensor) -> Tensor:
            return t.to(device, non_blocking=non_blocking)

        return EventBatch(
            move(self.pix),
            move(self.p),
            move(self.dt),
            move(self.counts),
            move(self.t0_us),
            move(self.t1_us),
            self.width,
            self.height,
        )

    def pin_memory(self) -> EventBatch:
        """Page-locked copies, for asynchronous copies to a GPU (the DataLoader calls this)."""
        return EventBatch(
            self.pix.pin_memory(),
            self.p.pin_memory(),
            self.dt.pin_memory(),
            self.counts.pin_memory(),
            self.t0_us.pin_memory(),
            self.t1_us.pin_memory(),
            self.width,
            self.height,
        )

    def window_of_event(self) -> Tensor:
        """int64 window index of every event (no host sync: the output size is known)."""
        ids = torch.arange(self.size, device=self.device)
        return torch.repeat_interleave(ids, self.counts, output_size=int(self.pix.shape[0]))

    def span_us(self) -> Tensor:
        """t1 - t0 per window (int64, >= 0)."""
        return self.t1_us - self.t0_us


def voxel_grid(batch: EventBatch, bins: int, *, normalize: bool = False) -> Tensor:
    """(N, bins, H, W) float32 voxel grids, one per window (see the module docstring)."""
    if bins < 1:
        raise ValueError(f"bins must be >= 1, got {bins}")
    n, npix = batch.size, batch.width * batch.height
    out = torch.zeros(n * bins * npix, dtype=torch.float32, device=batch.device)
    win = batch.window_of_event()
    pix = batch.pix.to(torch.int64)
    pol = batch.p.to(torch.float64)
    base = win * (bins * npix) + pix
    if bins == 1:
        out.index_add_(0, base, pol.to(torch.float32))
    else:
        duration = batch.span_us().clamp(min=1).to(torch.float64)[win]
        tn = (batch.dt.to(torch.float64) / duration) * (bins - 1)
        lo = torch.floor(tn).to(torch.int64).clamp(0, bins - 1)
        frac = tn - lo.to(torch.float64)
        hi = (lo + 1).clamp(max=bins - 1)
        out.index_add_(0, base + lo * npix, (pol * (1.0 - frac)).to(torch.float32))
        out.index_add_(0, base + hi * npix, (pol * frac).to(torch.float32))
    grid = out.view(n, bins, batch.height, batch.width)
    return _standardize_nonzero(grid) if normalize else grid


def _standardize_nonzero(grid: Tensor) -> Tensor:
    """Each window's non-zero entries to zero mean, unit population std (float64 sums)."""
    flat = grid.reshape(grid.shape[0], -1)
    nz = flat != 0
    count = nz.sum(dim=1).clamp(min=1).to(torch.float64)
    vals = torch.where(nz, flat.to(torch.float64), 0.0)
    mean = vals.sum(dim=1) / count
    dev = torch.where(nz, vals - mean[:, None], 0.0)
    std = torch.sqrt((dev * dev).sum(dim=1) / count)
    std = torch.where(std > 0, std, torch.ones_like(std))
    return (dev / std[:, None]).to(torch.float32).view_as(grid)


def event_frame(batch: EventBatch, *, signed: bool = True) -> Tensor:
    """(N, H, W) float32: per-pixel sum of polarities, or 1 where any event fired."""
    n, npix = batch.size, batch.width * batch.height
    idx = batch.window_of_event() * npix + batch.pix.to(torch.int64)
    out = torch.zeros(n * npix, dtype=torch.float32, device=batch.device)
    if signed:
        out.index_add_(0, idx, batch.p.to(torch.float32))
    else:
        out.index_fill_(0, idx, 1.0)
    return out.view(n, batch.height, batch.width)


def time_surface(batch: EventBatch, *, tau_us: float = 10_000.0, t_ref_us: Any = None) -> Tensor:
    """(N, 2, H, W) float32 exp(-(t_ref - t_last) / tau), 0 where no event; channel 0 ON.

    `t_ref_us`: rig time per window (a sequence or tensor of N) or one for all; default each
    window's end."""
    if not tau_us > 0:
        raise ValueError(f"tau_us must be positive, got {tau_us}")
    n, npix = batch.size, batch.width * batch.height
    win = batch.window_of_event()
    idx = win * (2 * npix) + (batch.p < 0).to(torch.int64) * npix + batch.pix.to(torch.int64)
    sae = torch.full((n * 2 * npix,), -1.0, dtype=torch.float64, device=batch.device)
    sae.scatter_reduce_(0, idx, batch.dt.to(torch.float64), reduce="amax", include_self=True)
    if t_ref_us is None:
        ref = batch.span_us()
    else:
        t_ref = (
            t_ref_us.to(batch.device, torch.int64)
            if isinstance(t_ref_us, torch.Tensor)
            else torch.as_tensor(np.asarray(t_ref_us, np.int64), device=batch.device)
        )
        ref = t_ref.expand(n) - batch.t0_us
    sae = sae.view(n, 2, batch.height, batch.width)
    age = (ref.to(torch.float64).view(n, 1, 1, 1) - sae).clamp(min=0.0)
    return torch.where(sae >= 0, torch.exp(-age / float(tau_us)), 0.0).to(torch.float32)
