"""`file:///abs/clip.mp4` or `file:///abs/dir/` replay as an RGB camera.

A video is decoded through OpenCV (`cv2.VideoCapture`: mp4, avi, mkv, ... whatever its
FFmpeg reads); a folder replays its images (png, jpg, jpeg, bmp, tif, tiff) in natural name
order (`f2.png` before `f10.png`), all of one size. Frames come as rgb8 or mono8 as the
settings' `pixel_format` asks (by default rgb8, or mono8 for a folder of grayscale images).

Device timestamps (int64 us, the camera's own clock): for a video, the container's frame
times (`CAP_PROP_POS_MSEC`) while they are present and increasing, else frame index / fps
(`fps=` overrides the container's rate and ignores its frame times); for a folder, index / fps
(`fps=`, default 30) or `timestamps.txt` beside the images, one integer microsecond value a
line, one line per image, strictly increasing. `frame_counter` is the frame index.

The replay runs free (a file cannot hear a trigger wire): frames are paced at the recorded
rate on the host's monotonic clock (`pace=1`, `pace=0.5` half speed) or handed over as fast
as the reader takes them (`pace=0`). A full host queue holds the replay back instead of
dropping frames, so nothing recorded is ever lost. Each start() replays from the first
frame; `loop=1` starts over at the end with counters still increasing and timestamps shifted
by the recording's span plus one period. Without `loop` the acquisition ends after the last
frame: reads return None and `stats().delivered` holds the count.

Capabilities: FREE_RUN, SOFTWARE_SYNC (frames are matched to pulses by host time, like a UVC
camera's), DEVICE_TIMESTAMPS, FRAME_COUNTER and COLOR; never HARDWARE_TRIGGER, so the capture
preflight refuses `trigger_mode = "hardware"`, and never EXPOSURE_CONTROL.
"""

from __future__ import annotations

import importlib
import logging
import math
import re
import struct
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from drivers.base import Capability, RgbCamera
from drivers.cv_images import to_pixel_format
from drivers.lifecycle import END, Signal
from drivers.registry import DeviceSpec
from rigd.core.devices import DeviceInfo
from rigd.core.errors import BackendUnavailableError, ConfigError, DeviceError
from rigd.core.frames import Frame
from rigd.core.pixels import frame_shape
from rigd.core.settings import CameraSettings

log = logging.getLogger(__name__)

_PARAMS = {"pace", "loop", "fps", "buffers"}
IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"})
TIMESTAMPS_FILE = "timestamps.txt"
DEFAULT_FPS = 30.0
#: Frames decoded ahead of the reader; a full queue holds the replay back.
DEFAULT_QUEUE = 16

Image = np.ndarray[Any, Any]


def natural_key(name: str) -> list[Any]:
    """Sort key putting `f2.png` before `f10.png` (digit runs compare as numbers)."""
    return [int(part) if i % 2 else part.lower() for i, part in enumerate(re.split(r"(\d+)", name))]


def list_images(folder: Path) -> list[Path]:
    """The folder's image files (not hidden, not in subfolders) in natural name order."""
    files = [
        p
        for p in folder.iterdir()
        if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".") and p.is_file()
    ]
    return sorted(files, key=lambda p: (natural_key(p.name), p.name))


def read_timestamps(path: Path, n_images: int) -> list[int]:
    """Microsecond timestamps from `timestamps.txt`: one integer a line (blank lines skipped),
    one per image, strictly increasing. ConfigError naming the file and line otherwise."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read: {getattr(exc, 'strerror', None) or exc}") from exc
    out: list[int] = []
    prev_line = 0
    for lineno, line in enumerate(text.splitlines(), 1):
        value = line.strip()
        if not value:
            continue
        try:
            t = int(value)
        except ValueError:
            raise ConfigError(
                f"{path} line {lineno}: {value[:40]!r} is not an integer timestamp in microseconds"
            ) from None
        if out and t <= out[-1]:
            raise ConfigError(
                f"{path} line {lineno}: {t} is not after {out[-1]} on line {prev_line} "
                "(timestamps must increase)"
            )
        out.append(t)
        prev_line = lineno
    if len(out) != n_images:
        raise ConfigError(f"{path}: {len(out)} timestamps for {n_images} images (want one line per image)")
    return out


def image_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG, JPEG or BMP header without decoding; None when the
    format is another or the header is not understood (the caller decodes instead)."""
    try:
        with path.open("rb") as f:
            head = f.read(32)
            if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
                w, h = struct.unpack(">II", head[16:24])
                return int(w), int(h)
            if head[:2] == b"BM" and len(head) >= 26:
                w, h = struct.unpack("<ii", head[18:26])
                return abs(int(w)), abs(int(h))
            if head[:2] == b"\xff\xd8":
                f.seek(2)
                return _jpeg_size(f)
    except (OSError, struct.error):
        return None
    return None


def _jpeg_size(f: Any) -> tuple[int, int] | None:
    """Walk the JPEG markers to the first start-of-frame segment."""
    while True:
        byte = f.read(1)
        while byte and byte != b"\xff":  # stray bytes between segments
            byte = f.read(1)
        while byte == b"\xff":  # fill bytes
            byte = f.read(1)
        if not byte:
            return None
        marker = byte[0]
        if marker == 0x01 or 0xD0 <= marker <= 0xD9:  # no length field
            continue
        length_bytes = f.read(2)
        if len(length_bytes) < 2:
            return None
        (length,) = struct.unpack(">H", length_bytes)
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            seg = f.read(5)
            if len(seg) < 5:
                return None
            _, h, w = struct.unpack(">BHH", seg)
            return int(w), int(h)
        f.seek(length - 2, 1)


class _Source:
    """Frames of one pass: `rewind()`, then `next_frame()` until it returns None."""

    label: str
    fps: float

    def rewind(self) -> None:
        raise NotImplementedError

    def next_frame(self, index: int, prev_us: int | None) -> tuple[Image, int] | None:
        """The next decoded image (BGR, BGRA or gray, 8 bit) and its raw timestamp (us)."""
        raise NotImplementedError

    def close(self) -> None:
        """Release what the pass holds."""


class _VideoSource(_Source):
    def __init__(self, path: Path, cv2: Any, fps: float | None) -> None:
        self.path, self._cv2 = path, cv2
        self.label = f"video {path}"
        self._cap: Any = None
        cap = self._open()
        try:
            ok, image = cap.read()
            if not ok or image is None:
                raise ConfigError(f"video {path}: OpenCV opened it but decodes no frame (empty or damaged?)")
            self.first: Image = image
            rate = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        finally:
            cap.release()
        self.use_container_times = fps is None
        if fps is not None:
            self.fps = fps
        elif math.isfinite(rate) and 0 < rate <= 10_000:
            self.fps = rate
        else:
            log.warning("video %s reports no frame rate (%r); assuming %g fps", path, rate, DEFAULT_FPS)
            self.fps = DEFAULT_FPS
        self._fallback: tuple[int, int] | None = None  # (index, us) index/fps counts on from

    def _open(self) -> Any:
        cap = self._cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            cap.release()
            raise ConfigError(
                f"video {self.path}: OpenCV cannot open it "
                "(not a video, damaged, or a codec its FFmpeg lacks)"
            )
        return cap

    def rewind(self) -> None:
        self.close()
        try:
            self._cap = self._open()
        except ConfigError as exc:  # it opened when the camera did: gone or changed since
            raise DeviceError(str(exc)) from None

    def next_frame(self, index: int, prev_us: int | None) -> tuple[Image, int] | None:
        if self._cap is None:
            return None
        ok, image = self._cap.read()
        if not ok or image is None:
            return None
        return image, self._timestamp(index, prev_us)

    def _timestamp(self, index: int, prev_us: int | None) -> int:
        if self.use_container_times:
            pos = float(self._cap.get(self._cv2.CAP_PROP_POS_MSEC))
            t = round(pos * 1000) if math.isfinite(pos) else -1
            if t >= 0 and (prev_us is None or t > prev_us):
                return t
            self.use_container_times = False
            if prev_us is not None:
                log.warning(
                    "%s: frame %d has no increasing container time (%r ms): index / fps from here on",
                    self.label,
                    index,
                    pos,
                )
                self._fallback = (index - 1, prev_us)
        base_index, base_us = self._fallback or (0, 0)
        return base_us + round((index - base_index) * 1e6 / self.fps)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class _FolderSource(_Source):
    def __init__(self, folder: Path, cv2: Any, fps: float | None) -> None:
        self.folder, self._cv2 = folder, cv2
        self.label = f"image folder {folder}"
        self.files = list_images(folder)
        if not self.files:
            raise ConfigError(
                f"image folder {folder} holds no images ({', '.join(sorted(s[1:] for s in IMAGE_SUFFIXES))})"
            )
        self.first: Image = self._decode(self.files[0], ConfigError)
        h, w = self.first.shape[:2]
        for p in self.files[1:]:
            size = image_size(p)
            if size is None:
                img = self._decode(p, ConfigError)
                size = (img.shape[1], img.shape[0])
            if size != (w, h):
                raise ConfigError(
                    f"image folder {folder}: {p.name} is {size[0]}x{size[1]}, not {w}x{h} like "
                    f"{self.files[0].name} (all images must be one size)"
                )
        self.size = (w, h)
        stamps = folder / TIMESTAMPS_FILE
        self.timestamps: list[int] | None = None
        if fps is None and stamps.is_file():
            self.timestamps = read_timestamps(stamps, len(self.files))
        elif fps is not None and stamps.is_file():
            log.info("%s: fps=%g given, %s ignored", self.label, fps, stamps)
        self.fps = fps if fps is not None else DEFAULT_FPS
        self._next = 0

    def _decode(self, path: Path, error: type[ConfigError] | type[DeviceError]) -> Image:
        cv2 = self._cv2
        try:
            data = np.fromfile(path, dtype=np.uint8)
        except OSError as exc:
            raise error(
                f"image folder {self.folder}: cannot read {path.name}: {exc.strerror or exc}"
            ) from exc
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        if image is None:
            raise error(f"image folder {self.folder}: cannot decode {path.name} (not an image, or damaged)")
        if image.dtype != np.uint8:
            raise error(
                f"image folder {self.folder}: {path.name} is {image.dtype} "
                "(the file camera replays 8-bit images)"
            )
        if image.ndim == 3 and image.shape[2] not in (1, 3, 4):
            raise error(f"image folder {self.folder}: {path.name} has {image.shape[2]} channels")
        return image

    def rewind(self) -> None:
        self._next = 0

    def next_frame(self, index: int, prev_us: int | None) -> tuple[Image, int] | None:
        i = self._next
        if i >= len(self.files):
            return None
        self._next += 1
        path = self.files[i]
        image = self.first.copy() if i == 0 else self._decode(path, DeviceError)
        if (image.shape[1], image.shape[0]) != self.size:
            raise DeviceError(
                f"image folder {self.folder}: {path.name} is {image.shape[1]}x{image.shape[0]}, "
                f"not {self.size[0]}x{self.size[1]} like {self.files[0].name}"
            )
        t = self.timestamps[i] if self.timestamps is not None else round(i * 1e6 / self.fps)
        return image, t


class FileCamera(RgbCamera):
    """Replays a video file or an image folder through the RgbCamera interface (free run)."""

    _capabilities = frozenset(
        {
            Capability.FREE_RUN,
            Capability.SOFTWARE_SYNC,
            Capability.DEVICE_TIMESTAMPS,
            Capability.FRAME_COUNTER,
            Capability.COLOR,
        }
    )

    def __init__(
        self,
        path: str | Path,
        *,
        pace: float = 1.0,
        loop: bool = False,
        fps: float | None = None,
        buffers: int = DEFAULT_QUEUE,
        spec: str = "",
        cv2_module: Any | None = None,
    ) -> None:
        self.path = Path(path)
        if not math.isfinite(pace) or pace < 0:
            raise ConfigError(f"file camera {self.path}: pace must be >= 0, got {pace}")
        if fps is not None and not (math.isfinite(fps) and fps > 0):
            raise ConfigError(f"file camera {self.path}: fps must be > 0, got {fps}")
        if buffers < 1:
            raise ConfigError(f"file camera {self.path}: buffers must be >= 1, got {buffers}")
        super().__init__(CameraSettings(trigger_mode="free_run"), queue_len=buffers, join_timeout_s=2.0)
        try:
            self._cv2 = cv2_module if cv2_module is not None else importlib.import_module("cv2")
        except ImportError as exc:
            raise BackendUnavailableError(
                f"file:// cameras need OpenCV ({exc}): pip install opencv-contrib-python-headless"
            ) from exc
        self.pace, self.loop = pace, loop
        source: _VideoSource | _FolderSource
        if self.path.is_dir():
            source = _FolderSource(self.path, self._cv2, fps)
            kind = "image folder"
            timing = TIMESTAMPS_FILE if source.timestamps is not None else f"index / {source.fps:g} fps"
        elif self.path.is_file():
            if self.path.suffix.lower() in IMAGE_SUFFIXES:
                raise ConfigError(
                    f"file camera {self.path}: a single image, not a video; "
                    f"name its folder to replay images (file://{self.path.parent}/)"
                )
            source = _VideoSource(self.path, self._cv2, fps)
            kind = "video"
            timing = (
                "container frame times (CAP_PROP_POS_MSEC), else index / fps"
                if source.use_container_times
                else f"index / {source.fps:g} fps"
            )
        elif self.path.exists():
            raise ConfigError(f"file camera {self.path}: neither a video file nor a folder of images")
        else:
            raise ConfigError(f"file camera {self.path}: no such file or folder")
        self._source: _Source = source
        self._first: Image = source.first
        self._label = f"file camera {self.path}"
        self._height, self._width = self._first.shape[:2]
        gray = self._first.ndim == 2 or self._first.shape[2] == 1
        self._default_format = "mono8" if gray else "rgb8"
        self._info = DeviceInfo(
            kind="rgb_camera",
            spec=spec or f"file://{self.path}",
            vendor="file",
            model=kind,
            facts={
                "sync": "software",
                "timestamps": timing,
                "source": kind,
                "frame_size": f"{self._width}x{self._height}",
                "fps": f"{source.fps:g}",
                "pace": f"{pace:g}",
                "loop": str(int(loop)),
                "backend": f"opencv {getattr(self._cv2, '__version__', '?')}",
            },
        )
        self._space = threading.Event()
        self._recorded: list[int] = []  # the first pass's raw timestamps, reused by later ones
        self._n_in_file: int | None = None
        self._passes = 0
        self._index = 0  # frame counter since start
        self._in_pass = 0
        self._shift = 0
        self._t0_host = 0.0
        self._t_first: int | None = None
        self._pending: tuple[Image, int] | None = None
        self._ended = False

    # -- identity -------------------------------------------------------------------------
    @property
    def pixel_format(self) -> str:
        return self._settings.pixel_format or self._default_format

    @property
    def frame_shape(self) -> tuple[int, ...]:
        return frame_shape(self._height, self._width, self.pixel_format)

    @property
    def frame_dtype(self) -> np.dtype[np.generic]:
        return np.dtype(np.uint8)

    # -- lifecycle ------------------------------------------------------------------------
    def _do_configure(self, settings: CameraSettings) -> None:
        if settings.pixel_format == "bayer_rg8":
            raise ConfigError(
                f"{self.label}: pixel_format 'bayer_rg8' cannot be delivered: image files and videos "
                "hold decoded images, not a sensor's raw mosaic (use rgb8 or mono8)"
            )
        if settings.gain_db:
            log.info("%s: gain_db=%g ignored (a recording's gain is its own)", self.label, settings.gain_db)

    def _do_start(self) -> None:
        self._queue.drain()  # frames of a previous run the reader left: this one starts over
        self._source.rewind()
        self._passes, self._index, self._in_pass, self._shift = 1, 0, 0, 0
        self._t_first, self._pending, self._ended = None, None, False
        self._t0_host = time.monotonic()

    def _do_stop(self) -> None:
        self._space.set()  # a grab waiting for room returns at once

    def _do_close(self) -> None:
        self._source.close()

    def _counters(self) -> tuple[int, dict[str, int]]:
        extra = {"passes": self._passes}
        if self._n_in_file is not None:
            extra["frames_in_file"] = self._n_in_file
        return 0, extra

    def _read(self, timeout_s: float) -> Frame | None:
        frame = super()._read(timeout_s)
        if frame is not None:
            self._space.set()
        return frame

    # -- replay (acquisition thread) ------------------------------------------------------
    def _next_image(self) -> tuple[Image, int] | None:
        """The next image and its timestamp with the loop's shift; None at the very end."""
        while True:
            prev = self._recorded[self._in_pass - 1] if self._in_pass else None
            got = self._source.next_frame(self._in_pass, prev)
            if got is not None:
                image, raw = got
                if self._in_pass < len(self._recorded):
                    raw = self._recorded[self._in_pass]
                else:
                    self._recorded.append(raw)
                self._in_pass += 1
                return image, raw + self._shift
            if self._in_pass == 0:
                return None  # a pass without a frame: the input is gone, do not spin
            if self._n_in_file is None or self._in_pass > self._n_in_file:
                self._n_in_file = self._in_pass
            if not self.loop:
                return None
            n = self._in_pass
            span = self._recorded[n - 1] - self._recorded[0]
            period = round(span / (n - 1)) if n > 1 else round(1e6 / self._source.fps)
            self._shift += span + max(1, period)
            self._passes += 1
            self._in_pass = 0
            self._source.rewind()
            log.debug("%s: pass %d, timestamps shifted by %d us", self.label, self._passes, self._shift)

    def _grab(self, timeout_s: float) -> Frame | Signal | None:
        if self._ended:
            return END
        if self._pending is None:
            self._pending = self._next_image()
            if self._pending is None:
                self._ended = True
                self._source.close()
                log.info("%s: end of the recording after %d frame(s)", self.label, self._index)
                return END
        image, t_us = self._pending
        if self._t_first is None:
            self._t_first = t_us
        if self.pace > 0:
            wait = self._t0_host + (t_us - self._t_first) / 1e6 / self.pace - time.monotonic()
            if wait > 0:
                time.sleep(min(wait, timeout_s))
                if wait > timeout_s:
                    return None
        self._space.clear()
        if len(self._queue) >= self._queue.maxlen:  # the reader is behind: hold the replay back
            self._space.wait(timeout_s)
            return None
        settings = self._settings
        frame = Frame(
            image=to_pixel_format(image, self.pixel_format, self._cv2),
            t_exposure_start_us=int(t_us),
            exposure_us=settings.exposure_us,
            frame_counter=self._index,
            host_time_ns=time.monotonic_ns(),
        )
        self._pending = None
        self._index += 1
        return frame


def _path_of(spec: DeviceSpec) -> str:
    path = (spec.location + spec.path) if spec.location else spec.path
    if not path:
        raise ConfigError(f"device spec {spec.raw!r}: no file or folder path")
    return path


def open_file_camera(spec: DeviceSpec) -> FileCamera:
    """Factory for `file:///abs/clip.mp4?pace=1&loop=0&fps=` and `file:///abs/dir/?fps=30`."""
    spec.check_params(_PARAMS)
    return FileCamera(
        _path_of(spec),
        pace=spec.float_param("pace", 1.0),
        loop=bool(spec.int_param("loop", 0)),
        fps=spec.float_param("fps", 0.0) if "fps" in spec.params else None,
        buffers=spec.int_param("buffers", DEFAULT_QUEUE),
        spec=spec.raw,
    )
