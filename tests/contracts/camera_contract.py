"""The contract every `RgbCamera` backend must pass.

Subclass `RgbCameraContract` and provide two fixtures: `camera` (an opened, stopped
camera in hardware-trigger mode) and `pulse` (a callable `pulse(n)` that makes the rig's
trigger fire n pulses at a rate the camera can follow, and returns when they are out).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from drivers.base import AcquisitionStats, Capability, RgbCamera
from rigd.core.errors import DeviceError
from rigd.core.frames import Frame
from rigd.core.settings import CameraSettings

Pulse = Callable[[int], object]
EXPOSURE_US = 1000


def read_n(camera: RgbCamera, n: int, timeout_s: float = 3.0) -> list[Frame]:
    frames: list[Frame] = []
    while len(frames) < n:
        f = camera.read_frame(timeout_s)
        if f is None:
            break
        frames.append(f)
    return frames


class RgbCameraContract:
    """Behaviour the daemon relies on, whatever camera sits behind the interface."""

    def _start(self, camera: RgbCamera) -> None:
        camera.configure(CameraSettings(trigger_mode="hardware", exposure_us=EXPOSURE_US))
        camera.start()

    def test_info_kind_and_capabilities(self, camera: RgbCamera) -> None:
        assert camera.kind == "rgb_camera"
        assert camera.info.kind == "rgb_camera"
        assert camera.info.spec
        caps = camera.capabilities
        assert isinstance(caps, frozenset)
        assert all(isinstance(c, Capability) for c in caps)
        assert Capability.HARDWARE_TRIGGER in caps, "the rig needs one frame per trigger pulse"

    def test_frame_shape_and_dtype(self, camera: RgbCamera) -> None:
        shape = camera.frame_shape
        assert len(shape) in (2, 3)
        assert all(s > 0 for s in shape)
        if len(shape) == 3:
            assert shape[2] == 3
        assert isinstance(camera.frame_dtype, np.dtype)

    def test_one_frame_per_pulse_in_order(self, camera: RgbCamera, pulse: Pulse) -> None:
        self._start(camera)
        pulse(6)
        frames = read_n(camera, 6)
        camera.stop()
        assert len(frames) == 6
        assert camera.read_frame(0.2) is None, "more frames than pulses"
        for f in frames:
            assert f.shape == camera.frame_shape
            assert f.image.dtype == camera.frame_dtype
            assert f.exposure_us == EXPOSURE_US
        stamps = [f.t_exposure_start_us for f in frames]
        assert all(isinstance(s, int) for s in stamps)
        assert stamps == sorted(stamps)
        assert len(set(stamps)) == 6
        if Capability.FRAME_COUNTER in camera.capabilities:
            counters = [f.frame_counter for f in frames]
            assert np.all(np.diff(counters) == 1), f"counter gaps without losses: {counters}"
        hosts = [f.host_time_ns for f in frames]
        assert hosts == sorted(hosts)
        st = camera.stats()
        assert isinstance(st, AcquisitionStats)
        assert st.delivered == 6
        assert st.device_dropped == 0

    def test_no_pulses_no_frames(self, camera: RgbCamera) -> None:
        self._start(camera)
        try:
            assert camera.read_frame(0.15) is None
        finally:
            camera.stop()

    def test_pulses_before_start_expose_nothing(self, camera: RgbCamera, pulse: Pulse) -> None:
        pulse(2)
        self._start(camera)
        try:
            assert camera.read_frame(0.15) is None
        finally:
            camera.stop()

    def test_buffered_frames_stay_readable_after_stop(self, camera: RgbCamera, pulse: Pulse) -> None:
        self._start(camera)
        pulse(3)
        camera.stop()
        assert len(read_n(camera, 3)) == 3

    def test_configure_only_while_stopped(self, camera: RgbCamera) -> None:
        self._start(camera)
        try:
            with pytest.raises(DeviceError):
                camera.configure(CameraSettings())
        finally:
            camera.stop()
        camera.configure(CameraSettings(exposure_us=2000))

    def test_stop_and_close_are_idempotent(self, camera: RgbCamera) -> None:
        camera.stop()
        self._start(camera)
        camera.stop()
        camera.stop()
        camera.close()
        camera.close()
