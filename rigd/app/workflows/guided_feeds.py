"""Live image feeds for guided calibration: a camera's newest frame, or an event sensor's events
reconstructed into a gray image the e2calib way.

Why a feed: the guided session (calibration.guided) only needs an image and its time. A camera
gives frames; an event sensor gives events, which `calibration.e2calib` turns into images. The
live reconstruction is e2calib's ``hpf`` (per-pixel leaky integration of log intensity, 1 Hz
corner): it forgets history within about a second, so the last EVENT_HISTORY_US of events give
the same image as the whole stream would, at a cost bounded by that window. The offline
``integrate`` method (more accurate, see docs/calibration.md) needs the whole stream and stays with
`rigd calibrate events` on a take.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import Protocol, TypeVar

import numpy as np
from numpy.typing import NDArray

from calibration.e2calib import ReconstructionParams, detector_image, reconstruct
from drivers.base import EventSensor, RgbCamera, Trigger
from drivers.registry import open_device
from rigd.app.config import CameraConfig, EventSensorConfig, RigConfig
from rigd.core.events import EventArray
from rigd.core.pixels import to_rgb

log = logging.getLogger(__name__)

DevT = TypeVar("DevT", RgbCamera, EventSensor)

#: Events kept for the live reconstruction (the hpf history decays within ~1/(2 pi 1 Hz)).
EVENT_HISTORY_US = 2_000_000
#: New events a live event image waits for (its period, in the sensor's time).
EVENT_FRAME_US = 100_000
#: Live reconstruction method (see the module docstring).
EVENT_METHOD = "hpf"


class ImageFeed(Protocol):
    """Newest image (gray or colour) and its time in the device clock, or None on timeout."""

    size: tuple[int, int]
    skipped: int
    exposure_us: float | None
    """What smears a moving board (None: no exposure, events)."""
    still_px: float | None
    """How still the board must be for a view (None: the session's option)."""

    def read(self, timeout_s: float) -> tuple[NDArray[np.uint8], int] | None: ...

    def close(self) -> None: ...


def shutdown(trigger: Trigger, device: RgbCamera | EventSensor) -> None:
    """Stop and close both devices; one failing must not keep the other running."""
    for stop in (trigger.stop, device.stop, device.close, trigger.close):
        try:
            stop()
        except Exception as exc:  # noqa: BLE001  (shutdown must reach every device)
            log.error("guided: %s failed during shutdown: %s", stop.__qualname__, exc)


class CameraFeed:
    """The newest frame of a started camera: older ones are skipped, a live feed must not lag
    (`newest_only=False`: every frame, in order, for a sim on virtual time)."""

    def __init__(
        self, trigger: Trigger, cam: RgbCamera, *, newest_only: bool = True, exposure_us: float | None = None
    ) -> None:
        self.trigger, self.cam = trigger, cam
        self.exposure_us = exposure_us
        self.still_px: float | None = None
        shape = cam.frame_shape
        self.size = (int(shape[1]), int(shape[0]))
        self.skipped = 0
        self.newest_only = newest_only

    def read(self, timeout_s: float) -> tuple[NDArray[np.uint8], int] | None:
        frame = self.cam.read_frame(timeout_s)
        if frame is None:
            return None
        while self.newest_only and (newer := self.cam.read_frame(0.0)) is not None:
            frame, self.skipped = newer, self.skipped + 1
        self.trigger.read_pulses(0.0)  # nobody needs the pulse records; keep the queue short
        # A Bayer camera's mosaic is demosaiced: the board is found in (and shown from) RGB.
        return np.asarray(to_rgb(np.asarray(frame.image), frame.pixel_format)), int(frame.t_exposure_start_us)

    def close(self) -> None:
        shutdown(self.trigger, self.cam)


class EventFeed:
    """Images reconstructed from a started event sensor's recent events (module docstring)."""

    def __init__(self, trigger: Trigger, sensor: EventSensor) -> None:
        self.trigger, self.sensor = trigger, sensor
        self.size = sensor.geometry
        self.exposure_us: float | None = None
        # Events need the board to move: a reconstruction has no exposure to smear in.
        self.still_px: float | None = math.inf
        self.skipped = 0
        self.params = ReconstructionParams()
        self._parts: list[EventArray] = []
        self._last_image_t: int | None = None

    def read(self, timeout_s: float) -> tuple[NDArray[np.uint8], int] | None:
        deadline = time.monotonic() + timeout_s
        while True:
            packet = self.sensor.read_events(max(0.0, deadline - time.monotonic()))
            self.trigger.read_pulses(0.0)
            if packet is not None and packet.n_events:
                self._parts.append(packet.events)
            t_end = self._t_end()
            if t_end is not None and (
                self._last_image_t is None or t_end - self._last_image_t >= EVENT_FRAME_US
            ):
                break
            if time.monotonic() >= deadline:
                return None
        events = EventArray.concatenate(self._parts)
        keep = np.flatnonzero(events.t >= t_end - EVENT_HISTORY_US)
        events = events[keep]
        self._parts = [events]
        self._last_image_t = t_end
        img = reconstruct(events, self.size, [t_end], EVENT_METHOD, self.params)[0]
        return detector_image(img, EVENT_METHOD, self.params), t_end

    def _t_end(self) -> int | None:
        last = [int(p.t[-1]) for p in self._parts if len(p)]
        return max(last) if last else None

    def close(self) -> None:
        shutdown(self.trigger, self.sensor)


def _open_trigger(rig: RigConfig) -> Trigger:
    trigger = open_device("trigger", rig.trigger.spec)
    try:
        trigger.configure(rig.trigger.settings)
    except BaseException:
        trigger.close()
        raise
    return trigger


def _open_started(
    rig: RigConfig, open_dev: Callable[[], DevT], configure: Callable[[DevT], None]
) -> tuple[Trigger, DevT]:
    """Open and configure the trigger, then the device; start the device, then the pulses
    (rigd.app.capture's order). What opened is stopped and closed again when a step fails."""
    trigger = _open_trigger(rig)
    try:
        device = open_dev()
    except BaseException:
        trigger.close()
        raise
    try:
        configure(device)
        device.start()
        trigger.arm()
        trigger.start()
    except BaseException:
        shutdown(trigger, device)
        raise
    return trigger, device


def open_camera_feed(rig: RigConfig, cam_cfg: CameraConfig, *, newest_only: bool = True) -> CameraFeed:
    """The started trigger and camera's feed."""
    trigger, cam = _open_started(
        rig, lambda: open_device("rgb_camera", cam_cfg.spec), lambda c: c.configure(cam_cfg.settings)
    )
    return CameraFeed(trigger, cam, newest_only=newest_only, exposure_us=cam_cfg.settings.exposure_us)


def open_event_feed(rig: RigConfig, sensor_cfg: EventSensorConfig) -> EventFeed:
    """The started trigger and event sensor's feed."""
    trigger, sensor = _open_started(
        rig, lambda: open_device("event_sensor", sensor_cfg.spec), lambda s: s.configure(sensor_cfg.settings)
    )
    return EventFeed(trigger, sensor)
