"""The guided session's camera feed: a Bayer camera's mosaic reaches the board detector (and the
console's picture) demosaiced."""

from __future__ import annotations

from unittest.mock import MagicMock

import numpy as np

from rigd.app.workflows.guided_feeds import CameraFeed
from rigd.core.frames import Frame
from rigd.core.pixels import demosaic, mosaic_rggb


def test_camera_feed_demosaics_a_bayer_frame() -> None:
    rgb = np.random.default_rng(2).integers(0, 256, (36, 64, 3), dtype=np.uint8)
    mosaic = mosaic_rggb(rgb)
    cam = MagicMock()
    cam.frame_shape = (36, 64)
    cam.read_frame.side_effect = [Frame(mosaic, 1234, 100, 0, 0, pixel_format="bayer_rg8"), None]
    feed = CameraFeed(MagicMock(), cam)
    assert feed.size == (64, 36)
    got = feed.read(0.1)
    assert got is not None
    image, t_us = got
    assert t_us == 1234
    np.testing.assert_array_equal(image, demosaic(mosaic))


def test_camera_feed_passes_mono_frames_as_they_are() -> None:
    gray = np.arange(36 * 64, dtype=np.uint8).reshape(36, 64)
    cam = MagicMock()
    cam.frame_shape = (36, 64)
    cam.read_frame.side_effect = [Frame(gray, 5, 100, 0, 0), None]
    got = CameraFeed(MagicMock(), cam).read(0.1)
    assert got is not None
    np.testing.assert_array_equal(got[0], gray)
