"""Dense tensors from a window of events: what learning code and the intensity/flow steps consume.

All functions take an `EventArray`, the sensor size and an optional window [t0_us, t1_us]
(default: the events' first and last time). Events outside the window or off the sensor are ignored,
so a slice of a longer stream can be passed as is. Times are normalised *relative to the window
start* by subtracting in int64 first and only then converting to float64: timestamps hours into a
take (~1e10 us) keep their microsecond resolution (float32 of 1e10 would be off by ~500 us).
A window of zero duration (all events at one time) counts as duration 1 us, so outputs stay finite.

Representations (Gallego et al. survey, Gehrig et al. EST):

* `event_frame`: per-pixel sum of polarities (signed) or event presence (`signed=False`).
* `count_image`: (2, H, W) per-polarity counts, channel 0 ON, channel 1 OFF.
* `surface_of_active_events`: (2, H, W) last timestamp per pixel/polarity, us since window start
  (-1 where no event).
* `time_surface`: (2, H, W) exp(-(t_ref - t_last) / tau), 0 where no event.
* `voxel_grid`: (B, H, W) polarity spread over B time bins with bilinear weights (Zhu et al.).
* `est_grid`: (2, B, H, W) per-polarity counts convolved in time with a trilinear, alpha or
  exponential kernel (EST's hand-designed kernels), sampled at the B bin centres.

Scatter-adds are `np.bincount` over flat indices (vectorized, no per-event Python loop), except
the voxel grid, one numba pass into float32 (`voxel_kernel`; `voxel_grid_bincount` is its numpy
reference). `reconstruction.torch_representations` builds the voxel grid, event frame and time
surface in torch, on the device a model runs on, with the same conventions.
"""

from __future__ import annotations

import logging
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from reconstruction.voxel_kernel import clear, reset_entries, standardize_nonzero, voxel_accumulate
from rigd.core.events import EventArray

log = logging.getLogger(__name__)

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
_NO_TRACKING = np.zeros(0, np.int64)
Kernel = Literal["trilinear", "alpha", "exponential"]


def window_bounds(
    ev: EventArray, width: int, height: int, t0_us: int | None, t1_us: int | None
) -> tuple[int, int]:
    """The window (t0, t1), both inclusive, that the representations use: the given bounds or
    the events' first and last time; refuses a non-positive sensor size or t1 < t0."""
    if width <= 0 or height <= 0:
        raise ValueError(f"sensor size must be positive, got {width}x{height}")
    n = len(ev)
    t0 = int(t0_us) if t0_us is not None else (int(ev.t.min()) if n else 0)
    t1 = int(t1_us) if t1_us is not None else (int(ev.t.max()) if n else t0)
    if t1 < t0:
        raise ValueError(f"window end {t1} us is before its start {t0} us")
    return t0, t1


def _window(
    ev: EventArray, width: int, height: int, t0_us: int | None, t1_us: int | None
) -> tuple[EventArray, int, int]:
    """Events inside the window and on the sensor, with the resolved (t0, t1)."""
    t0, t1 = window_bounds(ev, width, height, t0_us, t1_us)
    if len(ev):
        keep = (ev.t >= t0) & (ev.t <= t1) & (ev.x < width) & (ev.y < height)
        if not keep.all():
            ev = ev[keep]
    return ev, t0, t1


def _normalized_time(ev: EventArray, t0: int, t1: int) -> F64:
    """Event times in [0, 1] over the window, computed as float64 of int64 differences."""
    duration = max(t1 - t0, 1)
    return (ev.t - np.int64(t0)).astype(np.float64) / float(duration)


def _pixel_index(ev: EventArray, width: int) -> NDArray[np.int64]:
    return ev.y.astype(np.int64) * width + ev.x.astype(np.int64)


def _polarity_pixel_index(ev: EventArray, width: int, height: int) -> NDArray[np.int64]:
    """Flat index into a (2, H, W) array: channel 0 ON, channel 1 OFF."""
    return _pixel_index(ev, width) + (ev.p < 0).astype(np.int64) * (width * height)


def event_frame(
    ev: EventArray,
    width: int,
    height: int,
    t0_us: int | None = None,
    t1_us: int | None = None,
    *,
    signed: bool = True,
) -> F32:
    """(H, W) sum of polarities, or 1 where any event fired when `signed` is False."""
    ev, _, _ = _window(ev, width, height, t0_us, t1_us)
    idx = _pixel_index(ev, width)
    if signed:
        img = np.bincount(idx, weights=ev.p.astype(np.float64), minlength=width * height)
    else:
        img = (np.bincount(idx, minlength=width * height) > 0).astype(np.float64)
    return img.reshape(height, width).astype(np.float32)


def count_image(
    ev: EventArray, width: int, height: int, t0_us: int | None = None, t1_us: int | None = None
) -> F32:
    """(2, H, W) event counts: channel 0 ON, channel 1 OFF."""
    ev, _, _ = _window(ev, width, height, t0_us, t1_us)
    idx = _polarity_pixel_index(ev, width, height)
    return np.bincount(idx, minlength=2 * width * height).reshape(2, height, width).astype(np.float32)


def surface_of_active_events(
    ev: EventArray, width: int, height: int, t0_us: int | None = None, t1_us: int | None = None
) -> F64:
    """(2, H, W) time of the last event per pixel and polarity, us since t0; -1 where none.

    float64 so that windows of any length keep microsecond resolution. The maximum per pixel is
    taken with `np.maximum.at`, so the input need not be sorted.
    """
    ev, t0, _ = _window(ev, width, height, t0_us, t1_us)
    out = np.full(2 * width * height, -1.0, np.float64)
    idx = _polarity_pixel_index(ev, width, height)
    np.maximum.at(out, idx, (ev.t - np.int64(t0)).astype(np.float64))
    return out.reshape(2, height, width)


def time_surface(
    ev: EventArray,
    width: int,
    height: int,
    t0_us: int | None = None,
    t1_us: int | None = None,
    *,
    tau_us: float = 10_000.0,
    t_ref_us: int | None = None,
) -> F32:
    """(2, H, W) exponentially decayed surface exp(-(t_ref - t_last) / tau), 0 where no event.

    t_ref defaults to the window end: the most recent pixels are 1, older ones fade with time
    constant tau (the HOTS/HATS time surface without the spatial neighbourhood).
    """
    if not tau_us > 0:
        raise ValueError(f"tau_us must be positive, got {tau_us}")
    ev, t0, t1 = _window(ev, width, height, t0_us, t1_us)
    sae = surface_of_active_events(ev, width, height, t0, t1)
    ref = float((t_ref_us if t_ref_us is not None else t1) - t0)
    age = np.maximum(ref - sae, 0.0)
    return np.where(sae >= 0, np.exp(-age / tau_us), 0.0).astype(np.float32)


def voxel_grid(
    ev: EventArray,
    width: int,
    height: int,
    bins: int,
    t0_us: int | None = None,
    t1_us: int | None = None,
    *,
    normalize: bool = False,
    out: F32 | None = None,
) -> F32:
    """(B, H, W) voxel grid: each event adds its polarity to the two nearest bins, bilinear in time.

    Bin k sits at normalised time k / (B - 1) (one bin: everything goes to bin 0). With
    `normalize`, non-zero entries are standardised (zero mean, unit std) as in E2VID's input.
    One numba pass over the events into a float32 grid (`voxel_kernel`); the same values as
    `voxel_grid_bincount` to float32 rounding, without its copies and float64 grid. At
    1280x720x5 the grid is 18.4 MB and zeroing it costs about what the events do, so a loop over
    windows can pass the previous grid as `out` (C-contiguous float32 (B, H, W)): it is cleared
    by reading it and rewriting only its non-zero 512-byte blocks, then refilled and returned.
    `VoxelGridder` goes further (it resets only what it wrote) when a read-only view will do.
    """
    if bins < 1:
        raise ValueError(f"bins must be >= 1, got {bins}")
    t0, t1 = window_bounds(ev, width, height, t0_us, t1_us)
    if out is None:
        # calloc: memory the allocator recycles (the last grid) is zeroed by memset, at the
        # memory's write speed; a fresh mapping comes zeroed from the kernel.
        out = np.zeros((bins, height, width), np.float32)
    else:
        if out.dtype != np.float32 or out.shape != (bins, height, width) or not out.flags.c_contiguous:
            raise ValueError(
                f"out must be C-contiguous float32 of shape {(bins, height, width)}, "
                f"got {out.dtype} {out.shape}"
            )
        clear(out.reshape(-1).view(np.uint32))
    voxel_accumulate(ev.x, ev.y, ev.p, ev.t, t0, t1, width, height, bins, out.reshape(-1), _NO_TRACKING)
    if normalize:
        standardize_nonzero(out)
    return out


class VoxelGridder:
    """Voxel grids of one sensor and bin count into one buffer it keeps, for a CPU loop over
    windows: each call zeroes only the entries the previous call wrote instead of a whole new
    grid (18 MB at 1280x720x5, which costs more than the events). The same values as
    `voxel_grid`, bit for bit. The grid returned is a read-only view of the buffer, valid until
    the next call: copy it to keep it.
    """

    def __init__(self, width: int, height: int, bins: int) -> None:
        if bins < 1:
            raise ValueError(f"bins must be >= 1, got {bins}")
        window_bounds(EventArray.empty(), width, height, 0, 0)  # checks the sensor size
        self.width, self.height, self.bins = int(width), int(height), int(bins)
        self._flat = np.zeros(bins * height * width, np.float32)
        self._touched = np.zeros(0, np.int64)
        self._n_touched = 0

    def __call__(
        self, ev: EventArray, t0_us: int | None = None, t1_us: int | None = None, *, normalize: bool = False
    ) -> F32:
        t0, t1 = window_bounds(ev, self.width, self.height, t0_us, t1_us)
        reset_entries(self._flat, self._touched, self._n_touched)
        self._n_touched = 0
        if self._touched.shape[0] < 2 * len(ev):
            self._touched = np.zeros(2 * len(ev), np.int64)
        self._n_touched = voxel_accumulate(
            ev.x, ev.y, ev.p, ev.t, t0, t1, self.width, self.height, self.bins, self._flat, self._touched
        )
        grid = self._flat.reshape(self.bins, self.height, self.width)
        if normalize:
            standardize_nonzero(grid)  # changes only non-zero entries, all of them recorded
        view = grid.view()
        view.flags.writeable = False
        return view


def voxel_grid_bincount(
    ev: EventArray,
    width: int,
    height: int,
    bins: int,
    t0_us: int | None = None,
    t1_us: int | None = None,
    *,
    normalize: bool = False,
) -> F32:
    """`voxel_grid` as vectorized numpy (float64 `np.bincount`, then float32): the reference the
    kernel and the torch version are tested against, and the baseline of the training-reader
    benchmark."""
    if bins < 1:
        raise ValueError(f"bins must be >= 1, got {bins}")
    ev, t0, t1 = _window(ev, width, height, t0_us, t1_us)
    npix = width * height
    if bins == 1:
        grid = np.bincount(_pixel_index(ev, width), weights=ev.p.astype(np.float64), minlength=npix)
        out = grid.reshape(1, height, width)
    else:
        tn = _normalized_time(ev, t0, t1) * (bins - 1)
        lo = np.clip(np.floor(tn).astype(np.int64), 0, bins - 1)
        frac = tn - lo
        hi = np.minimum(lo + 1, bins - 1)
        pix = _pixel_index(ev, width)
        pol = ev.p.astype(np.float64)
        idx = np.concatenate([lo * npix + pix, hi * npix + pix])
        w = np.concatenate([pol * (1.0 - frac), pol * frac])
        out = np.bincount(idx, weights=w, minlength=bins * npix).reshape(bins, height, width)
    if normalize:
        nz = out != 0
        if nz.any():
            mean, std = out[nz].mean(), out[nz].std()
            out = np.where(nz, (out - mean) / (std if std > 0 else 1.0), 0.0)
    return out.astype(np.float32)


def _kernel_weights(d: F64, kernel: Kernel) -> F64:
    """Kernel value at time offset d (bin time minus event time, in units of the bin spacing)."""
    if kernel == "trilinear":
        return np.maximum(0.0, 1.0 - np.abs(d))
    dpos = np.maximum(d, 0.0)
    if kernel == "alpha":
        # Causal alpha function, peak 1 one bin spacing after the event.
        return np.where(d >= 0, dpos * np.exp(1.0 - dpos), 0.0)
    if kernel == "exponential":
        return np.where(d >= 0, np.exp(-dpos), 0.0)
    raise ValueError(f"unknown kernel {kernel!r} (trilinear, alpha, exponential)")


def est_grid(
    ev: EventArray,
    width: int,
    height: int,
    bins: int,
    t0_us: int | None = None,
    t1_us: int | None = None,
    *,
    kernel: Kernel = "trilinear",
) -> F32:
    """(2, B, H, W) EST-style grid: per-polarity event measurements convolved with a time kernel.

    Bin k samples time k / (B - 1) of the window; the kernel's width is one bin spacing. The
    trilinear kernel reproduces a per-polarity voxel grid of counts; alpha and exponential are
    causal (an event only contributes to later bins) and carry how long ago a pixel fired.
    """
    if bins < 1:
        raise ValueError(f"bins must be >= 1, got {bins}")
    _kernel_weights(np.zeros(1), kernel)  # validates the name even for an empty window
    ev, t0, t1 = _window(ev, width, height, t0_us, t1_us)
    npix = width * height
    spacing = max(bins - 1, 1)
    tn = _normalized_time(ev, t0, t1) * spacing
    pix = _pixel_index(ev, width) + (ev.p < 0).astype(np.int64) * npix
    out = np.empty((2, bins, height, width), np.float32)
    for k in range(bins):
        w = _kernel_weights(k - tn, kernel)
        out[:, k] = np.bincount(pix, weights=w, minlength=2 * npix).reshape(2, height, width)
    return out
