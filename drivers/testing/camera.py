"""The contracts every `RgbCamera` backend runs.

`CameraLifecycleContract` holds what any camera must do; a backend runs it through the
subclass for its trigger mode: `HardwareTriggerCameraContract` (fixtures `camera`, an opened
and stopped camera, and `pulse`, a callable `pulse(n)` that makes the rig's trigger fire n
pulses at a rate the camera can follow and returns when they are out) or
`FreeRunCameraContract` (fixture `camera` only).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import ClassVar

import numpy as np
import pytest
from pydantic import BaseModel

from drivers.base import AcquisitionStats, Capability, RgbCamera
from drivers.testing.lifecycle import Acquiring, AcquiringDeviceContract
from rigd.core.frames import Frame
from rigd.core.settings import CameraSettings

Pulse = Callable[[int], object]
EXPOSURE_US = 1000


def read_n(camera: RgbCamera, n: int, timeout_s: float = 3.0) -> list[Frame]:
    """Up to n frames, each awaited at most `timeout_s`."""
    frames: list[Frame] = []
    while len(frames) < n:
        f = camera.read_frame(timeout_s)
        if f is None:
            break
        frames.append(f)
    return frames


def drain(camera: RgbCamera, quiet_s: float = 0.2) -> list[Frame]:
    """Every frame still buffered, until none arrives for `quiet_s`."""
    out: list[Frame] = []
    while (f := camera.read_frame(quiet_s)) is not None:
        out.append(f)
    return out


class CameraLifecycleContract(AcquiringDeviceContract):
    """What the daemon relies on from any camera: identity, capabilities that hold, the state
    machine, well-formed frames. `settings` is how the suite starts the camera; `make_frames(n)`
    makes a started camera expose n frames."""

    settings: ClassVar[CameraSettings]

    @pytest.fixture
    def device(self, camera: RgbCamera) -> RgbCamera:
        return camera

    @pytest.fixture
    def make_frames(self) -> Pulse:
        raise NotImplementedError("the trigger-mode contract provides make_frames")

    def _read(self, device: Acquiring, timeout_s: float) -> object | None:
        assert isinstance(device, RgbCamera)
        return device.read_frame(timeout_s)

    def _asks(self) -> dict[Capability, BaseModel]:
        return {
            Capability.HARDWARE_TRIGGER: CameraSettings(trigger_mode="hardware"),
            Capability.FREE_RUN: CameraSettings(trigger_mode="free_run"),
            Capability.COLOR: self.settings.model_copy(update={"pixel_format": "rgb8"}),
            Capability.EXPOSURE_CONTROL: self.settings.model_copy(update={"exposure_us": 1234}),
        }

    def test_info_kind_and_capabilities(self, camera: RgbCamera) -> None:
        assert camera.kind == "rgb_camera"
        assert camera.info.kind == "rgb_camera"
        assert camera.info.spec
        caps = camera.capabilities
        assert isinstance(caps, frozenset)
        assert all(isinstance(c, Capability) for c in caps)
        hardware, software = Capability.HARDWARE_TRIGGER in caps, Capability.SOFTWARE_SYNC in caps
        assert hardware != software, "a camera is synced either by a trigger wire or by host time"
        assert Capability.HARDWARE_TRIGGER in caps or Capability.FREE_RUN in caps

    def test_frame_shape_and_dtype(self, camera: RgbCamera) -> None:
        shape = camera.frame_shape
        assert len(shape) in (2, 3)
        assert all(s > 0 for s in shape)
        if len(shape) == 3:
            assert shape[2] == 3
        assert isinstance(camera.frame_dtype, np.dtype)

    def test_frames_are_well_formed(self, camera: RgbCamera, make_frames: Pulse) -> None:
        self._start(camera)
        make_frames(4)
        frames = read_n(camera, 4)
        camera.stop()
        frames += drain(camera)
        assert len(frames) >= 4
        for f in frames:
            assert f.shape == camera.frame_shape
            assert f.image.dtype == camera.frame_dtype
            assert f.exposure_us == self.settings.exposure_us
            assert isinstance(f.t_exposure_start_us, int)
        stamps = [f.t_exposure_start_us for f in frames]
        assert stamps == sorted(stamps)
        assert len(set(stamps)) == len(stamps)
        if Capability.FRAME_COUNTER in camera.capabilities:
            counters = [f.frame_counter for f in frames]
            assert np.all(np.diff(counters) == 1), f"counter gaps without losses: {counters}"
        hosts = [f.host_time_ns for f in frames]
        assert hosts == sorted(hosts)
        st = camera.stats()
        assert isinstance(st, AcquisitionStats)
        assert st.delivered == len(frames)
        assert st.device_dropped == 0

    def test_buffered_frames_stay_readable_after_stop(self, camera: RgbCamera, make_frames: Pulse) -> None:
        self._start(camera)
        make_frames(3)
        time.sleep(0.1)
        camera.stop()
        assert len(read_n(camera, 3)) == 3


class HardwareTriggerCameraContract(CameraLifecycleContract):
    """One frame per trigger pulse, none without: needs fixtures `camera` and `pulse`."""

    settings = CameraSettings(trigger_mode="hardware", exposure_us=EXPOSURE_US)

    @pytest.fixture
    def make_frames(self, pulse: Pulse) -> Pulse:
        return pulse

    def test_has_a_trigger_input(self, camera: RgbCamera) -> None:
        assert Capability.HARDWARE_TRIGGER in camera.capabilities, "the rig needs one frame per pulse"

    def test_one_frame_per_pulse_in_order(self, camera: RgbCamera, pulse: Pulse) -> None:
        self._start(camera)
        pulse(6)
        frames = read_n(camera, 6)
        camera.stop()
        assert len(frames) == 6
        assert camera.read_frame(0.2) is None, "more frames than pulses"
        assert len({f.t_exposure_start_us for f in frames}) == 6
        st = camera.stats()
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


class FreeRunCameraContract(CameraLifecycleContract):
    """Frames on the camera's own clock, without pulses: needs fixture `camera`."""

    settings = CameraSettings(trigger_mode="free_run", exposure_us=EXPOSURE_US, free_run_fps=50.0)

    @pytest.fixture
    def make_frames(self) -> Pulse:
        return lambda n: None  # a free-running camera exposes on its own

    def test_runs_free(self, camera: RgbCamera) -> None:
        assert Capability.FREE_RUN in camera.capabilities

    def test_frames_keep_coming_until_stop(self, camera: RgbCamera) -> None:
        self._start(camera)
        first = read_n(camera, 3)
        camera.stop()
        drain(camera)
        assert len(first) == 3
        assert camera.read_frame(0.2) is None, "frames after stop and drain"
