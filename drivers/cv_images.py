"""OpenCV images as takes store them: OpenCV reads gray, BGR or BGRA; frames are mono8 (H, W)
or rgb8 (H, W, 3), contiguous. Shared by the backends that read through OpenCV."""

from __future__ import annotations

from typing import Any

import numpy as np

Image = np.ndarray[Any, Any]


def to_pixel_format(image: Image, fmt: str | None, cv2: Any) -> Image:
    """An OpenCV image (gray, BGR or BGRA) as contiguous mono8 (H, W) when `fmt` says so, else rgb8
    (H, W, 3)."""
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if fmt == "mono8":
        if image.ndim == 2:
            return np.ascontiguousarray(image)
        code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        return np.ascontiguousarray(cv2.cvtColor(image, code))
    if image.ndim == 2:
        return np.ascontiguousarray(cv2.cvtColor(image, cv2.COLOR_GRAY2RGB))
    code = cv2.COLOR_BGRA2RGB if image.shape[2] == 4 else cv2.COLOR_BGR2RGB
    return np.ascontiguousarray(cv2.cvtColor(image, code))
