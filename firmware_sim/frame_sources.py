"""Frame sources for the frames-to-events simulator: arrays, a video, a folder of images or a
take's camera, each an iterator of (frame, t_us) with what is known about it up front."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from rigd.take.reader import Take

log = logging.getLogger(__name__)

AnyFrame = NDArray[Any]
IMAGE_EXTENSIONS = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp"})


@dataclass(slots=True)
class FrameSource:
    """An iterator of (frame, t_us) with what is known about it up front."""

    frames: Iterator[tuple[AnyFrame, int]]
    n_frames: int | None
    fps: float | None
    description: str
    size: tuple[int, int] | None = None
    """(width, height) of the frames when known before reading them."""
    _cleanup: list[Callable[[], None]] = field(default_factory=list)

    def close(self) -> None:
        for fn in self._cleanup:
            fn()
        self._cleanup.clear()


def _times(fps: float, t0_us: int = 0) -> Iterator[int]:
    i = 0
    while True:
        yield t0_us + round(i * 1e6 / fps)
        i += 1


def array_source(
    frames: Iterable[AnyFrame], *, fps: float | None = None, timestamps_us: Iterable[int] | None = None
) -> FrameSource:
    """Frames from memory (a (N, H, W[, C]) array or any iterable of arrays, e.g. a generator)."""
    if (fps is None) == (timestamps_us is None):
        raise ValueError("array_source: give exactly one of fps or timestamps_us")
    if fps is not None and not (fps > 0 and math.isfinite(fps)):
        raise ValueError(f"array_source: fps must be positive, got {fps}")
    times: Iterable[int] = _times(fps) if fps is not None else timestamps_us  # type: ignore[assignment]
    n = len(frames) if isinstance(frames, np.ndarray | list | tuple) else None
    return FrameSource(zip(iter(frames), iter(times), strict=False), n, fps, "in-memory frames")


def _bgr_to_rgb(img: AnyFrame) -> AnyFrame:
    if img.ndim == 3 and img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if img.ndim == 3 and img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
    return img


def video_source(path: str | Path, *, fps: float | None = None) -> FrameSource:
    """Frames of a video file (cv2.VideoCapture); fps overrides the file's frame rate."""
    p = Path(path)
    cap = cv2.VideoCapture(str(p))
    if not cap.isOpened():
        raise ValueError(f"{p}: cannot open as a video (OpenCV VideoCapture failed)")
    file_fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    use_fps = fps if fps is not None else file_fps
    if not (use_fps > 0 and math.isfinite(use_fps)):
        cap.release()
        raise ValueError(f"{p}: the video reports no frame rate; pass --fps")
    count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
    size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))

    def gen() -> Iterator[tuple[AnyFrame, int]]:
        times = _times(use_fps)
        try:
            while True:
                ok, img = cap.read()
                if not ok:
                    return
                yield _bgr_to_rgb(img), next(times)
        finally:
            cap.release()

    return FrameSource(gen(), count if count > 0 else None, use_fps, f"video {p}", size, [cap.release])


def folder_source(path: str | Path, *, fps: float) -> FrameSource:
    """Images of a folder in sorted file-name order, at `fps`."""
    p = Path(path)
    if not (fps > 0 and math.isfinite(fps)):
        raise ValueError(f"{p}: an image folder needs a positive --fps, got {fps}")
    files = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_EXTENSIONS and f.is_file())
    if not files:
        raise ValueError(f"{p}: no image files ({', '.join(sorted(IMAGE_EXTENSIONS))})")

    def gen() -> Iterator[tuple[AnyFrame, int]]:
        for f, t in zip(files, _times(fps), strict=False):
            img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise ValueError(f"{f}: cannot read as an image")
            yield _bgr_to_rgb(img), t

    return FrameSource(gen(), len(files), fps, f"image folder {p} ({len(files)} images)")


def take_source(path: str | Path, *, camera: str | None = None) -> FrameSource:
    """RGB frames of one camera of a take, with their stored exposure-start times."""
    p = Path(path)
    take = Take(p)
    stack = ExitStack()
    stack.callback(take.close)
    try:
        cams = take.cameras
        if not cams:
            raise ValueError(f"{p}: the take has no cameras")
        cam = camera if camera is not None else cams[0]
        if cam not in cams:
            raise ValueError(f"{p}: no camera {cam!r} in the take (cameras: {', '.join(cams)})")
        series = take.camera(cam)
        ts = series.timestamps_us
    except BaseException:
        stack.close()
        raise
    n = len(series)
    fps = (n - 1) * 1e6 / float(ts[-1] - ts[0]) if n > 1 and ts[-1] > ts[0] else None
    shape = series.shape

    def gen() -> Iterator[tuple[AnyFrame, int]]:
        with stack:
            for i in range(n):
                yield np.asarray(series[i].image), int(ts[i])

    return FrameSource(gen(), n, fps, f"take {p} camera {cam}", (shape[1], shape[0]), [stack.close])


def open_source(path: str | Path, *, fps: float | None = None, camera: str | None = None) -> FrameSource:
    """A video file, an image folder or a take (.h5/.hdf5), by what `path` is."""
    p = Path(path)
    if not p.exists():
        raise ValueError(f"{p}: no such file or folder")
    if p.is_dir():
        if fps is None:
            raise ValueError(f"{p}: an image folder has no frame rate; pass --fps")
        return folder_source(p, fps=fps)
    if p.suffix.lower() in (".h5", ".hdf5"):
        if fps is not None:
            log.warning("%s: --fps ignored for a take (its frames carry their own times)", p)
        return take_source(p, camera=camera)
    return video_source(p, fps=fps)
