"""The tasks of `rigd reconstruct`: each reads one bounded piece of a take and returns a small result.

They are plain functions of picklable arguments, so the same task graph runs on local threads,
local processes or a `dask.distributed` cluster. Each opens the take itself (an open HDF5 file
cannot travel between processes) and reads at most one block of events plus a short warm-up.

Exactness of the block-wise filter: the background-activity filter keeps an event when enough
neighbours fired within `window_us` before it (every event updating its pixel's time), so an
event's fate depends only on the events of the `window_us` before it. A block filtered after a
warm-up of that span gives exactly what filtering the whole stream gives (tested).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from reconstruction.e2i import EventIntegrator
from reconstruction.filters import BackgroundActivityFilter
from reconstruction.partition import interval_maps
from rigd.core.errors import TakeFormatError
from rigd.core.events import EventArray
from rigd.core.layout import Events, event_group
from rigd.take.reader import Take

log = logging.getLogger(__name__)

#: High-pass snapshots integrate this many time constants (1 / (2 pi f_c)) before the keyframe:
#: older events weigh at most e^-10 (4.5e-5) of their contrast, far below one event's 0.3.
HIGHPASS_WARMUP_TAU = 10.0


class FilterKnobs(BaseModel):
    """The background-activity filter (paper: r = 3 px, 30 us, 2 same-polarity neighbours)."""

    model_config = ConfigDict(frozen=True)

    enabled: bool = True
    window_us: int = Field(30, ge=1, le=1 << 29)
    radius_px: int = Field(3, ge=1, le=8)
    min_support: int = Field(2, ge=0, le=48)

    def make(self, width: int, height: int) -> BackgroundActivityFilter:
        return BackgroundActivityFilter(
            width, height, radius_px=self.radius_px, window_us=self.window_us, min_support=self.min_support
        )

    @property
    def warmup_us(self) -> int:
        return self.window_us if self.enabled else 0


@dataclass(frozen=True, slots=True)
class Grid:
    """The rig-time windows activity is counted in: [t0 + k w, t0 + (k + 1) w), k < n."""

    t0_us: int
    window_us: int
    n: int


@dataclass(frozen=True, slots=True)
class BlockScan:
    """What one block of events [lo, hi) of a sensor held, and its kept events per grid window."""

    sensor: str
    lo: int
    hi: int
    t_first_us: int
    t_last_us: int
    n_events: int
    n_kept: int
    k0: int
    """Grid index of counts[0]."""
    counts: NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class BlockMaps:
    """Signed kept-event maps of the cut intervals [cuts[i0 + k], cuts[i0 + k + 1]) one block touches."""

    sensor: str
    i0: int
    maps: NDArray[np.int32]
    n_events: int


@dataclass(frozen=True, slots=True)
class Snapshot:
    """One sensor's log-intensity image at one keyframe, and the events read for it."""

    sensor: str
    t_us: int
    image: NDArray[np.float32]
    n_events: int


def _check_order(path: Path, sensor: str, t: NDArray[np.int64], first_index: int) -> None:
    """TakeFormatError naming the take, dataset and index where event times go backwards."""
    back = np.flatnonzero(np.diff(t) < 0)
    if len(back):
        bad = first_index + int(back[0]) + 1
        raise TakeFormatError(
            f"{path}: /{event_group(sensor)}/{Events.T}: event times go backwards at index {bad} "
            "(damaged take)"
        )


def _read_filtered(
    take: Take, sensor: str, lo: int, hi: int, filt: FilterKnobs
) -> tuple[EventArray, EventArray]:
    """(kept events of [lo, hi), all of them), checking time order and warming the filter up."""
    path = take.path
    start = max(lo - 1, 0)  # one event before the block: the order check then covers every pair
    series = take.sensor(sensor)
    ev = series.by_index(start, hi)
    _check_order(path, sensor, ev.t, start)
    ev = ev[lo - start :]
    if len(ev) == 0 or not filt.enabled:
        return ev, ev
    w, h = series.geometry
    warm = EventArray.empty()
    if lo > 0:
        j = min(series.index(int(ev.t[0]) - filt.warmup_us), lo)
        warm = series.by_index(j, lo)
    keep = filt.make(w, h).mask(EventArray.concatenate([warm, ev]) if len(warm) else ev)
    return ev[keep[len(warm) :]], ev


def scan_block(path: Path, sensor: str, lo: int, hi: int, grid: Grid, filt: FilterKnobs) -> BlockScan:
    """Filter one block and count its kept events per grid window (phase 1: the activity)."""
    with Take(path) as take:
        kept, block = _read_filtered(take, sensor, lo, hi, filt)
    n = len(block)
    k = (kept.t - np.int64(grid.t0_us)) // grid.window_us
    k = np.clip(k, 0, grid.n - 1)
    if len(k):
        k0 = int(k[0])
        counts = np.bincount(k - k0).astype(np.int64)
    else:
        k0, counts = 0, np.zeros(0, np.int64)
    t_first = int(block.t[0]) if n else grid.t0_us
    t_last = int(block.t[-1]) if n else grid.t0_us
    log.debug("%s %s [%d, %d): %d of %d kept", path, sensor, lo, hi, len(kept), n)
    return BlockScan(sensor, lo, hi, t_first, t_last, n, len(kept), k0, counts)


def map_block(
    path: Path,
    sensor: str,
    lo: int,
    hi: int,
    cuts: NDArray[np.int64],
    i0: int,
    filt: FilterKnobs,
    scale: float,
) -> BlockMaps:
    """Signed kept-event maps of one block per cut interval it touches (phase 2: the keyframes).

    `cuts` are the cut times from index `i0` on that the block's events fall between.
    """
    with Take(path) as take:
        kept, block = _read_filtered(take, sensor, lo, hi, filt)
        w, h = take.sensor(sensor).geometry
    return BlockMaps(sensor, i0, interval_maps(kept, w, h, cuts, scale), len(block))


def highpass_warmup_us(cutoff_hz: float) -> int:
    """How far before a keyframe a high-pass snapshot starts integrating (HIGHPASS_WARMUP_TAU)."""
    return math.ceil(HIGHPASS_WARMUP_TAU / (2.0 * math.pi * cutoff_hz) * 1e6)


def snapshot(
    path: Path,
    sensor: str,
    t_from_us: int,
    t_us: int,
    filt: FilterKnobs,
    method: str,
    contrast: float,
    cutoff_hz: float,
    block_events: int,
) -> Snapshot:
    """Log intensity at `t_us` integrated from the kept events of [t_from_us, t_us) (phase 3).

    Streams in blocks of `block_events` (one filter and one integrator carried across them), so
    memory does not grow with the span: a direct integration from a long segment's start reads
    the whole segment once, in bounded pieces.
    """
    with Take(path) as take:
        series = take.sensor(sensor)
        w, h = series.geometry
        lo = series.index(t_from_us - filt.warmup_us)
        start = series.index(t_from_us)
        hi = series.index(t_us)
        baf = filt.make(w, h) if filt.enabled else None
        integ = EventIntegrator(w, h, method, contrast=contrast, cutoff_hz=cutoff_hz, t0_us=t_from_us)  # type: ignore[arg-type]
        for a in range(lo, hi, block_events):
            b = min(a + block_events, hi)
            ev = series.by_index(a, b)
            _check_order(path, sensor, ev.t, a)
            keep = baf.mask(ev) if baf is not None else np.ones(len(ev), np.bool_)
            keep[: max(0, start - a)] = False  # the filter's warm-up only
            integ.process(ev[keep])
        image = integ.snapshot(t_us).astype(np.float32)
    return Snapshot(sensor, t_us, image, hi - start)
