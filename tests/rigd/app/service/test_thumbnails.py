"""Live previews (rigd.app.service.thumbnails): a Bayer camera's (H, W) mosaic is shown in
colour, a mono8 frame of the same shape as gray."""

from __future__ import annotations

import cv2
import numpy as np

from rigd.app.service.thumbnails import frame_thumbnail
from rigd.core.frames import Frame
from rigd.core.pixels import mosaic_rggb


def _decoded(frame: Frame) -> np.ndarray:
    jpeg, w, h = frame_thumbnail(frame, 64, quality=95)
    img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)  # BGR
    assert img.shape == (h, w, 3)
    return img


def test_a_bayer_frame_previews_in_its_colours() -> None:
    rgb = np.zeros((72, 128, 3), np.uint8)
    rgb[...] = (230, 40, 20)  # red
    bayer = _decoded(Frame(mosaic_rggb(rgb), 0, 1, 0, 0, pixel_format="bayer_rg8"))
    b, g, r = (float(bayer[8:-8, 8:-8, k].mean()) for k in range(3))
    assert r > 200
    assert g < 60
    assert b < 60
    # The same bytes from a mono8 camera are a gray picture of the mosaic.
    mono = _decoded(Frame(mosaic_rggb(rgb), 0, 1, 0, 0))
    assert np.abs(mono[..., 0].astype(int) - mono[..., 2].astype(int)).max() <= 3


def test_preview_is_the_frame_shrunk() -> None:
    """Halving steps give what one INTER_AREA resize gives, to rounding."""
    from rigd.app.service.thumbnails import _resize

    yy, xx = np.mgrid[0:720, 0:1280]
    img = np.stack([xx % 256, yy % 256, (xx + yy) % 256], axis=-1).astype(np.uint8)
    direct = cv2.resize(img, (320, 180), interpolation=cv2.INTER_AREA)
    stepped = _resize(img, 320)
    assert stepped.shape == direct.shape
    assert np.abs(stepped.astype(int) - direct.astype(int)).max() <= 1
    assert _resize(img, 200).shape == (112, 200, 3)


def test_event_preview_colours_the_polarity_where_events_fell() -> None:
    from rigd.app.service.thumbnails import events_thumbnail
    from rigd.core.events import EventArray

    yy, xx = (a.ravel() for a in np.mgrid[0:32, 0:32])
    x = np.concatenate([xx + 64, xx + 960])
    y = np.concatenate([yy + 64, yy + 640])
    p = np.concatenate([np.ones(xx.size), np.zeros(xx.size)])
    ev = EventArray.from_arrays(x, y, p, np.arange(x.size))
    jpeg, w, h = events_thumbnail(ev, (1280, 720), 320, quality=100)
    assert (w, h) == (320, 180)
    img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR).astype(int)  # BGR
    on, off, grey = img[20, 20], img[164, 244], img[90, 160]
    assert on[2] - on[0] > 150  # red: ON
    assert off[0] - off[2] > 150  # blue: OFF
    assert np.abs(grey - 128).max() <= 3
