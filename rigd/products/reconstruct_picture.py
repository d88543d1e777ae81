"""`overview.png` of one reconstructed take: what `rigd reconstruct` found, at a glance.

`segments.json` and `snapshots.npz` are for programs; a person checking a run wants to see where
the segments fell on the motion and what the keyframes look like, as `rigd inspect --thumbnails`
shows a take. The picture has the kept-event rate of all sensors over the take (the signal the
segmentation cut) with the segment boundaries and keyframes drawn on it, and under it a row per
event sensor of keyframe snapshots (at most MAX_COLUMNS, evenly chosen: `picks`), each labelled
with its segment and time. The run keeps only those snapshots in memory as it streams the rest to
`snapshots.npz`. Drawn with OpenCV, as the calibration report's figures.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from reconstruction.partition import Segment
from rigd.core.errors import RigdError

log = logging.getLogger(__name__)

U8 = NDArray[np.uint8]

#: Width of the picture; keyframe columns at most; plot height.
WIDTH = 1600
MAX_COLUMNS = 8
PLOT_HEIGHT = 260
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_LABEL_BAR = 18


def rate_plot(
    counts: NDArray[np.int64], window_us: int, t0_us: int, segments: Sequence[Segment], width: int = WIDTH
) -> U8:
    """Kept events per second over the take, segment boundaries (grey) and keyframes (orange)."""
    img = np.full((PLOT_HEIGHT, width, 3), 255, np.uint8)
    left, right, top, bottom = 70, 15, 28, 30
    pw, ph = width - left - right, PLOT_HEIGHT - top - bottom
    rate = counts.astype(np.float64) / (window_us / 1e6)
    vmax = max(float(rate.max(initial=0.0)), 1.0)
    span_us = max(len(counts) * window_us, 1)

    def x_of(t_us: float) -> int:
        return left + round(pw * (t_us - t0_us) / span_us)

    cv2.putText(img, "kept events per second, all sensors", (left, 18), _FONT, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    label = f"max {vmax / 1e6:.2f} Mev/s" if vmax >= 1e5 else f"max {vmax:,.0f} ev/s"
    cv2.putText(img, label, (width - right - 170, 18), _FONT, 0.45, (80, 80, 80), 1, cv2.LINE_AA)
    cv2.rectangle(img, (left, top), (left + pw, top + ph), (0, 0, 0), 1)
    for seg in segments:
        x = x_of(seg.t_start_us)
        cv2.line(img, (x, top), (x, top + ph), (170, 170, 170), 1)
    if rate.size:
        xs = left + np.round(np.linspace(0, pw, rate.size)).astype(np.int32)
        ys = top + ph - np.round(ph * rate / vmax).astype(np.int32)
        cv2.polylines(
            img, [np.stack([xs, ys], axis=1).reshape(-1, 1, 2)], False, (180, 110, 30), 1, cv2.LINE_AA
        )
    for seg in segments:
        x = x_of(seg.keyframe_us)
        cv2.line(img, (x, top + ph - 8), (x, top + ph), (0, 120, 255), 2)
    seconds = span_us / 1e6
    step = next((s for s in (0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 30, 60, 120, 300) if seconds / s <= 10), 600)
    t = 0.0
    while t <= seconds + 1e-9:
        x = x_of(t0_us + t * 1e6)
        cv2.line(img, (x, top + ph), (x, top + ph + 4), (0, 0, 0), 1)
        cv2.putText(img, f"{t:g} s", (x - 10, top + ph + 18), _FONT, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        t += step
    n = len(segments)
    note = f"{n} segment{'s' if n != 1 else ''} (bounds grey), keyframe{'s' if n != 1 else ''} (orange)"
    cv2.putText(img, note, (left + 4, top + 14), _FONT, 0.4, (80, 80, 80), 1, cv2.LINE_AA)
    return img


def picks(n: int) -> list[int]:
    """Indices of the keyframes shown: at most MAX_COLUMNS of `n`, evenly spread, first and last."""
    if n <= 0:
        return []
    return sorted({round(float(v)) for v in np.linspace(0, n - 1, min(n, MAX_COLUMNS))})


def snapshot_row(
    sensor: str,
    shots: Sequence[tuple[int, NDArray[np.float32]]],
    segments: Sequence[Segment],
    t0_us: int,
    size: tuple[int, int],
) -> U8:
    """The picked keyframe snapshots (time, image) of one sensor of `size` (w, h), each stretched
    between its 1st and 99th percentile."""
    tile_w = WIDTH // MAX_COLUMNS
    w, h = size
    tile_h = max(1, round(tile_w * h / max(w, 1)))
    row = np.zeros((tile_h + _LABEL_BAR, WIDTH, 3), np.uint8)
    by_key = {seg.keyframe_us: seg.index for seg in segments}
    for col, (t_us, image) in enumerate(shots[:MAX_COLUMNS]):
        img = np.asarray(image, np.float32)
        lo, hi = np.percentile(img, (1, 99)) if img.size else (0.0, 1.0)
        gray = np.clip((img - lo) / max(float(hi - lo), 1e-9) * 255, 0, 255).astype(np.uint8)
        tile = cv2.resize(gray, (tile_w, tile_h), interpolation=cv2.INTER_AREA)
        x0 = col * tile_w
        row[_LABEL_BAR:, x0 : x0 + tile_w] = cv2.cvtColor(tile, cv2.COLOR_GRAY2BGR)
        seg = by_key.get(int(t_us))
        where = f"seg {seg} " if seg is not None else ""
        label = f"{sensor} {where}t={(int(t_us) - t0_us) / 1e6:.3f}s"
        cv2.putText(row, label, (x0 + 3, 13), _FONT, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    if not shots:
        cv2.putText(row, f"{sensor}: no snapshots", (3, 13), _FONT, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return row


def write_overview(
    out_png: Path,
    counts: NDArray[np.int64],
    window_us: int,
    t0_us: int,
    segments: Sequence[Segment],
    snapshots: dict[str, list[tuple[int, NDArray[np.float32]]]],
    sizes: dict[str, tuple[int, int]],
) -> Path:
    """The rate plot over the snapshot rows of every sensor, as one PNG (module docstring)."""
    parts = [rate_plot(counts, window_us, t0_us, segments)]
    for sensor, shots in snapshots.items():
        parts.append(snapshot_row(sensor, shots, segments, t0_us, sizes[sensor]))
    sheet = np.vstack(parts)
    if not cv2.imwrite(str(out_png), sheet):
        raise RigdError(f"could not write {out_png}")
    log.info("reconstruct: overview %s (%dx%d)", out_png, sheet.shape[1], sheet.shape[0])
    return out_png
