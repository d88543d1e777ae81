"""One camera frame and the timing facts the sync engine needs about it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True, slots=True)
class Frame:
    """A frame as delivered by a camera driver.

    `t_exposure_start_us` is in the camera's own clock until the sync engine maps it;
    `host_time_ns` is the host's monotonic clock when the driver received the frame,
    used only for coarse pulse matching, never as a timestamp. `pixel_format` says what the
    image holds where its shape cannot (`bayer_rg8`: a raw (H, W) mosaic, see rigd.core.pixels);
    None means mono8 for (H, W) and rgb8 for (H, W, 3).
    """

    image: NDArray[np.generic]
    t_exposure_start_us: int
    exposure_us: int
    frame_counter: int
    host_time_ns: int
    pulse_index: int = -1
    pixel_format: str | None = None

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.image.shape)
