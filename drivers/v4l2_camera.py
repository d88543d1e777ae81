"""`v4l2:///dev/videoN?width=&height=&fps=&fourcc=` through OpenCV's V4L2 capture, free-running.

UVC cameras have no trigger input: they run on their own clock and frames get **host**
timestamps (monotonic clock at reception, minus nothing: the exposure start is unknown to
within a frame period). The camera therefore advertises FREE_RUN and SOFTWARE_SYNC, never
HARDWARE_TRIGGER (`sync: software` in `DeviceInfo.facts` says the same in the take): its
frames are matched to trigger pulses by host time, not by a wire.

The base's acquisition thread reads continuously while started; when the reader is late the
host queue gives up its oldest frame, counted in `stats().extra["host_queue_dropped"]`.
"""

from __future__ import annotations

import importlib
import logging
import time
from typing import Any

import numpy as np

from drivers.base import Capability, RgbCamera
from drivers.cv_images import to_pixel_format
from drivers.registry import DeviceSpec
from rigd.core.devices import DeviceInfo
from rigd.core.errors import BackendUnavailableError, ConfigError, DeviceError
from rigd.core.frames import Frame
from rigd.core.pixels import frame_shape
from rigd.core.settings import CameraSettings

log = logging.getLogger(__name__)

_PARAMS = {"width", "height", "fps", "fourcc", "buffers"}
#: Frames kept for the reader before the oldest is dropped (counted).
DEFAULT_QUEUE = 64
#: Failed reads in a row (50 ms apart) after which the camera counts as unplugged.
_UNPLUGGED_AFTER = 20


def parse_v4l2_spec(spec: DeviceSpec) -> dict[str, Any]:
    """Validated node and capture parameters of a v4l2:// spec (no device needed)."""
    spec.check_params(_PARAMS)
    node = spec.path
    if spec.location or not node.startswith("/dev/"):
        raise ConfigError(f"device spec {spec.raw!r}: use v4l2:///dev/videoN (three slashes)")
    fourcc = spec.param("fourcc", "")
    if fourcc and len(fourcc) != 4:
        raise ConfigError(f"device spec {spec.raw!r}: fourcc must be 4 characters (MJPG, YUYV, ...)")
    out: dict[str, Any] = {
        "node": node,
        "width": spec.int_param("width", 0),
        "height": spec.int_param("height", 0),
        "fps": spec.float_param("fps", 0.0),
        "fourcc": fourcc,
        "buffers": spec.int_param("buffers", DEFAULT_QUEUE),
    }
    if out["width"] < 0 or out["height"] < 0 or out["fps"] < 0 or out["buffers"] < 1:
        raise ConfigError(f"device spec {spec.raw!r}: width, height, fps must be >= 0 and buffers >= 1")
    return out


class V4l2Camera(RgbCamera):
    """A UVC camera through cv2.VideoCapture(node, cv2.CAP_V4L2); free-run only."""

    _capabilities = frozenset(
        {Capability.FREE_RUN, Capability.SOFTWARE_SYNC, Capability.COLOR, Capability.EXPOSURE_CONTROL}
    )

    def __init__(
        self, spec: DeviceSpec, *, capture: Any | None = None, cv2_module: Any | None = None
    ) -> None:
        p = parse_v4l2_spec(spec)
        # The reader must get the newest frames: a full queue gives up its oldest (counted).
        super().__init__(
            CameraSettings(trigger_mode="free_run"), queue_len=p["buffers"], drop="oldest", join_timeout_s=2.0
        )
        self._spec = spec
        self.node: str = p["node"]
        self._label = f"V4L2 camera {self.node}"
        try:
            self._cv2 = cv2_module if cv2_module is not None else importlib.import_module("cv2")
        except ImportError as exc:
            raise BackendUnavailableError(
                f"v4l2:// needs OpenCV ({exc}): pip install opencv-contrib-python-headless"
            ) from exc
        cv2 = self._cv2
        cap = capture if capture is not None else cv2.VideoCapture(self.node, cv2.CAP_V4L2)
        if not cap.isOpened():
            raise DeviceError(
                f"cannot open V4L2 camera {self.node}: OpenCV could not open it (busy, no permission "
                "- are you in group video? - or not a capture node; `rigd devices`, `rigd doctor`)"
            )
        self._cap = cap
        if p["fourcc"]:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*p["fourcc"]))
        if p["width"]:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, p["width"])
        if p["height"]:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, p["height"])
        if p["fps"]:
            cap.set(cv2.CAP_PROP_FPS, p["fps"])
        self._width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        self._height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        if self._width <= 0 or self._height <= 0:
            cap.release()
            raise DeviceError(f"V4L2 camera {self.node}: driver reports no frame size")
        self._read_failures = 0
        self._failures = 0
        self._counter = 0
        self._info = DeviceInfo(
            kind="rgb_camera",
            spec=spec.raw,
            vendor="",
            model=_sysfs_name(self.node),
            facts={
                "sync": "software",
                "timestamps": "host monotonic clock at reception",
                "backend": f"opencv-v4l2 {getattr(cv2, '__version__', '?')}",
            },
        )

    @property
    def frame_shape(self) -> tuple[int, ...]:
        return frame_shape(self._height, self._width, self._settings.pixel_format or "rgb8")

    @property
    def frame_dtype(self) -> np.dtype[np.generic]:
        return np.dtype(np.uint8)

    def _do_configure(self, settings: CameraSettings) -> None:
        if settings.pixel_format == "bayer_rg8":
            raise ConfigError(
                f"V4L2 camera {self.node}: pixel_format 'bayer_rg8' cannot be delivered: OpenCV's "
                "V4L2 capture hands over decoded images, not the sensor's raw mosaic (use rgb8 or mono8)"
            )
        cv2, cap = self._cv2, self._cap
        cap.set(cv2.CAP_PROP_FPS, settings.free_run_fps)
        # UVC exposure is in 100 us units with auto-exposure off (V4L2 manual mode = 1).
        cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)
        if not cap.set(cv2.CAP_PROP_EXPOSURE, max(1, round(settings.exposure_us / 100))):
            log.warning("V4L2 camera %s: exposure not settable through OpenCV; use v4l2-ctl", self.node)
        if settings.gain_db:
            cap.set(cv2.CAP_PROP_GAIN, settings.gain_db)

    def _do_start(self) -> None:
        self._failures = 0

    def _grab(self, timeout_s: float) -> Frame | None:
        ok, image = self._cap.read()
        host_ns = time.monotonic_ns()
        if not ok or image is None:
            self._failures += 1
            self._read_failures += 1
            if self._failures >= _UNPLUGGED_AFTER:  # ~ a second of nothing: unplugged
                raise DeviceError(f"V4L2 camera {self.node}: no frames (unplugged?)")
            time.sleep(0.05)
            return None
        self._failures = 0
        cv2, settings = self._cv2, self._settings
        image = to_pixel_format(image, settings.pixel_format, cv2)
        frame = Frame(
            image=image,
            t_exposure_start_us=host_ns // 1000 - settings.exposure_us,
            exposure_us=settings.exposure_us,
            frame_counter=self._counter,
            host_time_ns=host_ns,
        )
        self._counter += 1
        return frame

    def _counters(self) -> tuple[int, dict[str, int]]:
        return 0, {"read_failures": self._read_failures}

    def _do_close(self) -> None:
        self._cap.release()


def _sysfs_name(node: str) -> str:
    try:
        with open(f"/sys/class/video4linux/{node.rsplit('/', 1)[-1]}/name", encoding="utf-8") as f:
            return f.read().strip()
    except OSError:
        return ""


def open_v4l2_camera(spec: DeviceSpec) -> V4l2Camera:
    """Factory for `v4l2:///dev/videoN?width=1280&height=720&fps=30&fourcc=MJPG`."""
    return V4l2Camera(spec)
