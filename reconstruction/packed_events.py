"""A window of events packed for shipping from a data-loader worker: 9 bytes an event.

A training job's workers read events; turning them into a dense float grid there and sending
that through worker IPC (18 MB for a 5-bin voxel grid at 1280x720, against ~0.6 MB of events
in a 50 ms window) is what starved the GPU (issue 24). So a worker packs the window's events
into a flat pixel index (int32, y * width + x), the polarity (int8, +1/-1) and the time since
the window start (int32 us), and `reconstruction.torch_representations` builds the grids on
the model's device. One numba pass (nogil); packing needs no torch.

Windows follow `reconstruction.representations`: both bounds inclusive, events outside them
ignored (a slice of a longer stream can be passed as is). Events inside the window but off the
sensor are not ignored silently: they are counted (`off_sensor`), since a take should have none.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from reconstruction.representations import window_bounds
from rigd.core.events import EventArray

log = logging.getLogger(__name__)

#: Longest window whose times fit the int32 `dt` (about 35 minutes).
MAX_WINDOW_US = 2**31 - 1


@dataclass(frozen=True, slots=True)
class PackedEvents:
    """One window's events: `pix` (int32 y * width + x), `p` (int8 +1/-1), `dt` (int32 us since
    `t0_us`); the window is [t0_us, t1_us], both inclusive, on a `width` x `height` sensor."""

    pix: NDArray[np.int32]
    p: NDArray[np.int8]
    dt: NDArray[np.int32]
    t0_us: int
    t1_us: int
    width: int
    height: int
    off_sensor: int = 0

    def __len__(self) -> int:
        return int(self.pix.shape[0])

    @property
    def nbytes(self) -> int:
        return int(self.pix.nbytes + self.p.nbytes + self.dt.nbytes)


# A numba kernel takes every event column as a parameter of its own: its signature is alike
# in shape to voxel_kernel's, with nothing to share.
@njit(nogil=True, cache=True)
def _pack_kernel(
    x: NDArray[np.uint16],
    y: NDArray[np.uint16],
    p: NDArray[np.int8],
    t: NDArray[np.int64],
    t0: int,
    t1: int,
    width: int,
    height: int,
    pix: NDArray[np.int32],
    pol: NDArray[np.int8],
    dt: NDArray[np.int32],
) -> tuple[int, int]:
    """Pack the events of [t0, t1] on the sensor into the outputs; (packed, off the sensor)."""
    k = 0
    off = 0
    for i in range(t.shape[0]):
        ti = t[i]
        if ti < t0 or ti > t1:
            continue
        xi = np.int32(x[i])
        yi = np.int32(y[i])
        if xi >= width or yi >= height:
            off += 1
            continue
        pix[k] = yi * np.int32(width) + xi
        pol[k] = p[i]
        dt[k] = np.int32(ti - t0)
        k += 1
    return k, off


def pack_events(
    ev: EventArray, width: int, height: int, t0_us: int | None = None, t1_us: int | None = None
) -> PackedEvents:
    """The events of [t0_us, t1_us] (default: first to last event) on the sensor, packed in one
    numba pass."""
    t0, t1 = window_bounds(ev, width, height, t0_us, t1_us)
    if t1 - t0 > MAX_WINDOW_US:
        raise ValueError(
            f"window [{t0}, {t1}] us is longer than {MAX_WINDOW_US} us: its times overflow int32"
        )
    if width * height > 2**31 - 1:
        raise ValueError(f"sensor {width}x{height} has too many pixels for an int32 pixel index")
    n = len(ev)
    pix, pol, dt = np.empty(n, np.int32), np.empty(n, np.int8), np.empty(n, np.int32)
    k, off = _pack_kernel(ev.x, ev.y, ev.p, ev.t, t0, t1, width, height, pix, pol, dt)
    if k < n:  # copies, so that shipping the arrays does not ship the unused rest
        pix, pol, dt = pix[:k].copy(), pol[:k].copy(), dt[:k].copy()
    if off:
        log.warning(
            "%d events of window [%d, %d] us lie off the %dx%d sensor; not packed",
            off,
            t0,
            t1,
            width,
            height,
        )
    return PackedEvents(pix, pol, dt, t0, t1, int(width), int(height), off)


@dataclass(frozen=True, slots=True)
class PackedBatch:
    """Windows of one sensor concatenated: `counts[i]` events of window i, in order; `t0_us`,
    `t1_us` (inclusive) per window."""

    pix: NDArray[np.int32]
    p: NDArray[np.int8]
    dt: NDArray[np.int32]
    counts: NDArray[np.int64]
    t0_us: NDArray[np.int64]
    t1_us: NDArray[np.int64]
    width: int
    height: int
    off_sensor: int


def concat_packed(windows: Sequence[PackedEvents]) -> PackedBatch:
    """One batch of windows of the same sensor geometry."""
    if not windows:
        raise ValueError("a batch needs at least one window")
    sizes = {(w.width, w.height) for w in windows}
    if len(sizes) != 1:
        raise ValueError(f"windows of a batch must share one sensor geometry, got {sorted(sizes)}")
    width, height = sizes.pop()
    return PackedBatch(
        np.concatenate([w.pix for w in windows]),
        np.concatenate([w.p for w in windows]),
        np.concatenate([w.dt for w in windows]),
        np.array([len(w) for w in windows], np.int64),
        np.array([w.t0_us for w in windows], np.int64),
        np.array([w.t1_us for w in windows], np.int64),
        width,
        height,
        sum(w.off_sensor for w in windows),
    )
