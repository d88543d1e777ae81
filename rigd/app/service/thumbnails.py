"""Small JPEG previews of the latest frame / recent events for the telemetry stream.

Cheap on purpose: the console renders them several times a second during a take, on the cores
the capture uses. Frames shrink in halving steps (OpenCV's INTER_AREA is several times faster
at exactly 2x than at 4x), and events are counted straight into the thumbnail's pixels (no
full-size image): ~1 ms each at 720p.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from rigd.core.events import EventArray
from rigd.core.frames import Frame
from rigd.core.pixels import to_rgb


def _resize(img: NDArray[np.uint8], width: int) -> NDArray[np.uint8]:
    h, w = img.shape[:2]
    if w <= width:
        return img
    height = max(1, round(h * width / w))
    while w >= 2 * width:  # exact halvings first: INTER_AREA's fast path
        w, h = w // 2, h // 2
        img = np.asarray(cv2.resize(img[: 2 * h, : 2 * w], (w, h), interpolation=cv2.INTER_AREA), np.uint8)
    if w == width and h == height:
        return np.asarray(img, dtype=np.uint8)
    return np.asarray(cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA), dtype=np.uint8)


def frame_thumbnail(frame: Frame, width: int, quality: int = 70) -> tuple[bytes, int, int]:
    """JPEG of a frame as it is viewed (a Bayer mosaic demosaiced), at most `width` wide."""
    img = np.asarray(to_rgb(np.asarray(frame.image), frame.pixel_format))
    if img.dtype != np.uint8:  # 16-bit and float formats: scale to 8 bit for the preview
        lo, hi = float(img.min()), float(img.max())
        img = ((img - lo) * (255.0 / max(hi - lo, 1e-9))).astype(np.uint8)
    small = _resize(img, width)
    if small.ndim == 3 and small.shape[2] == 3:
        small = np.ascontiguousarray(small[:, :, ::-1])  # RGB -> BGR for OpenCV
    ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes(), int(small.shape[1]), int(small.shape[0])


def events_thumbnail(
    events: EventArray, geometry: tuple[int, int], width: int, quality: int = 70
) -> tuple[bytes, int, int]:
    """ON events red, OFF events blue, on grey (the usual event-viewer colours), counted per
    thumbnail pixel (the majority polarity of the events falling in it), so a lone event stays
    visible instead of being averaged away by a resize."""
    w, h = geometry
    tw = min(width, w)
    th = max(1, round(h * tw / w))
    x = np.minimum(events.x.astype(np.int64) * tw // w, tw - 1)
    y = np.minimum(events.y.astype(np.int64) * th // h, th - 1)
    idx = y * tw + x
    pos = events.p > 0
    on = np.bincount(idx[pos], minlength=th * tw)
    off = np.bincount(idx[~pos], minlength=th * tw)
    img = np.full((th * tw, 3), 128, np.uint8)
    img[off > on] = (255, 80, 0)  # BGR blue-ish
    img[on > off] = (0, 60, 255)  # BGR red-ish
    small = img.reshape(th, tw, 3)
    ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes(), int(small.shape[1]), int(small.shape[0])
