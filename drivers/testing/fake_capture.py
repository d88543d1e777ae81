"""A stand-in for OpenCV's `cv2.VideoCapture`, for the V4L2 backend's tests without a camera."""

from __future__ import annotations

import time

import cv2
import numpy as np


class FakeCapture:
    """cv2.VideoCapture stand-in: BGR frames with a counter in pixel (0, 0); `unplug()` ends them."""

    def __init__(self, width: int = 64, height: int = 48) -> None:
        self.props: dict[int, float] = {cv2.CAP_PROP_FRAME_WIDTH: width, cv2.CAP_PROP_FRAME_HEIGHT: height}
        self.n = 0
        self.plugged = True
        self.released = False

    def isOpened(self) -> bool:  # noqa: N802 - OpenCV's name
        return True

    def set(self, prop: int, value: float) -> bool:
        self.props[prop] = value
        return True

    def get(self, prop: int) -> float:
        return self.props.get(prop, 0.0)

    def read(self) -> tuple[bool, np.ndarray | None]:
        time.sleep(0.005)
        if not self.plugged:
            return False, None
        img = np.zeros(
            (int(self.get(cv2.CAP_PROP_FRAME_HEIGHT)), int(self.get(cv2.CAP_PROP_FRAME_WIDTH)), 3), np.uint8
        )
        img[..., 0] = 255  # blue in BGR
        img[0, 0, 1] = self.n % 256
        self.n += 1
        return True, img

    def release(self) -> None:
        self.released = True
