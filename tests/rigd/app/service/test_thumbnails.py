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
