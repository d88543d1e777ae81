"""One camera's frames in a take, read one at a time: `Take.camera` returns a FrameSeries.

Bayer cameras are demosaiced here, on read, so the writer's hot path stores frames as sent."""

from __future__ import annotations

from collections.abc import Sequence
from typing import overload

import h5py
import numpy as np
from numpy.typing import NDArray

from rigd.core.errors import TakeError
from rigd.core.frames import Frame
from rigd.core.layout import FRAMES_GROUP, Frames
from rigd.core.pixels import BAYER_PATTERNS, is_bayer, stored_pixel_format, to_gray, to_rgb
from rigd.take.guard import OpenTake, OutOfRangeError, format_errors


@format_errors
class FrameSeries(Sequence[Frame]):
    """The frames of one camera; images are read one at a time on indexing.

    Frames come as they are viewed: a `bayer_rg8` camera's stored mosaics are demosaiced to
    (H, W, 3) RGB on read (about a millisecond per 720p frame), so export, previews, calibration
    and training need not know the format. `demosaic=False` gives what is stored, as `raw()` does.
    """

    def __init__(self, take: OpenTake, name: str, group: h5py.Group, demosaic: bool = True) -> None:
        self._take = take
        self.name = name
        self._g = group
        self._images: h5py.Dataset = group[Frames.IMAGES]
        self._n = int(self._images.shape[0])
        self._ts: NDArray[np.int64] | None = None
        self.pixel_format = stored_pixel_format(group.attrs, self.stored_shape, f"{take.path}: {group.name}")
        """As stored: mono8, rgb8 or bayer_rg8 (older takes: mono8 / rgb8 by the shape)."""
        self.demosaic = demosaic and is_bayer(self.pixel_format)
        """Whether indexing demosaics the stored frames."""

    def _where_file(self) -> str:
        return f"{self._take.path}: {self._g.name}"

    def __len__(self) -> int:
        return self._n

    @property
    def stored_shape(self) -> tuple[int, ...]:
        """(H, W) or (H, W, C) of a frame as stored (a Bayer frame is its (H, W) mosaic)."""
        return tuple(self._images.shape[1:])

    @property
    def shape(self) -> tuple[int, ...]:
        """(H, W) or (H, W, C) of the images indexing returns."""
        stored = self.stored_shape
        return (*stored, 3) if self.demosaic else stored

    @property
    def bayer_pattern(self) -> str | None:
        """Colour-filter layout of a Bayer camera (sensor naming, e.g. RGGB); None otherwise."""
        return BAYER_PATTERNS.get(self.pixel_format)

    def _index(self, i: int) -> int:
        k = int(i) + self._n if int(i) < 0 else int(i)
        if not 0 <= k < self._n:
            raise OutOfRangeError(f"frame {i} out of range for {self._n} frames of camera {self.name!r}")
        return k

    def raw(self, i: int) -> NDArray[np.generic]:
        """Image i as stored (a Bayer camera's mosaic)."""
        return np.asarray(self._images[self._index(i)])

    def rgb(self, i: int) -> NDArray[np.generic]:
        """Image i as (H, W, 3) RGB: demosaiced, or a mono frame's gray in all three channels."""
        img = to_rgb(self.raw(i), self.pixel_format)
        return np.repeat(img[:, :, None], 3, axis=2) if img.ndim == 2 else img

    def gray(self, i: int) -> NDArray[np.generic]:
        """Image i as (H, W) gray (demosaiced for a Bayer camera), what a board detector needs."""
        return to_gray(self.raw(i), self.pixel_format)

    @property
    def timestamps_us(self) -> NDArray[np.int64]:
        """Exposure start of every frame, in the take's time domain (rig once finalized)."""
        if self._ts is None:
            self._ts = np.asarray(self._g[Frames.T_EXPOSURE_START][: self._n], dtype=np.int64)
        return self._ts

    @overload
    def __getitem__(self, i: int) -> Frame: ...
    @overload
    def __getitem__(self, i: slice) -> Sequence[Frame]: ...
    def __getitem__(self, i: int | slice) -> Frame | Sequence[Frame]:
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(self._n))]
        k = self._index(i)
        g = self._g
        image = self._images[k]
        return Frame(
            image=to_rgb(image, self.pixel_format) if self.demosaic else image,
            t_exposure_start_us=int(self.timestamps_us[k]),
            exposure_us=int(g[Frames.EXPOSURE][k]),
            frame_counter=int(g[Frames.FRAME_COUNTER][k]),
            host_time_ns=int(g[Frames.HOST_TIME_NS][k]),
            pulse_index=int(g[Frames.PULSE_INDEX][k]),
            pixel_format="rgb8" if self.demosaic else self.pixel_format,
        )

    def index_at(self, t_us: int) -> int:
        """Index of the last frame whose exposure started at or before t_us; -1 if none."""
        self._take.require_rig(f"/{FRAMES_GROUP}/{self.name}")
        return int(np.searchsorted(self.timestamps_us, int(t_us), side="right")) - 1

    def nearest(self, t_us: int) -> int:
        """Index of the frame whose exposure start is closest to t_us (earlier one on ties)."""
        self._take.require_rig(f"/{FRAMES_GROUP}/{self.name}")
        ts = self.timestamps_us
        if ts.size == 0:
            raise TakeError(f"{self._take.path}: camera {self.name!r} has no frames")
        j = int(np.searchsorted(ts, int(t_us), side="left"))
        if j == 0:
            return 0
        if j == ts.size:
            return j - 1
        return j - 1 if int(t_us) - int(ts[j - 1]) <= int(ts[j]) - int(t_us) else j
