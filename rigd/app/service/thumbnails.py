"""Small JPEG previews of the latest frame / recent events for the telemetry stream."""

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
    """ON events red, OFF events blue, on grey (the usual event-viewer colours)."""
    w, h = geometry
    idx = events.y.astype(np.int64) * w + events.x.astype(np.int64)
    pos = events.p > 0
    on = np.bincount(idx[pos], minlength=h * w)
    off = np.bincount(idx[~pos], minlength=h * w)
    img = np.full((h * w, 3), 128, np.uint8)
    img[off > on] = (255, 80, 0)  # BGR blue-ish
    img[on > off] = (0, 60, 255)  # BGR red-ish
    small = _resize(img.reshape(h, w, 3), width)
    ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes(), int(small.shape[1]), int(small.shape[0])
