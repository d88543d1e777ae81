"""V4L2 backend: spec parsing and the grab loop with a stand-in capture; a real /dev/video* if present."""

from __future__ import annotations

import glob
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.base import Capability, RgbCamera
from drivers.registry import DeviceSpec
from drivers.testing.camera import FreeRunCameraContract
from drivers.testing.fake_capture import FakeCapture
from drivers.v4l2_camera import V4l2Camera, open_v4l2_camera, parse_v4l2_spec
from rigd.core.errors import ConfigError, DeviceError
from rigd.core.settings import CameraSettings


class TestV4l2StandIn(FreeRunCameraContract):
    """The free-run camera contract through OpenCV's code path, the stand-in capture in place
    of a UVC camera."""

    @pytest.fixture
    def camera(self) -> Iterator[RgbCamera]:
        cam = V4l2Camera(DeviceSpec.parse("v4l2:///dev/video9?width=64&height=48"), capture=FakeCapture())
        yield cam
        cam.close()


def test_spec_parsing() -> None:
    p = parse_v4l2_spec(DeviceSpec.parse("v4l2:///dev/video2?width=1280&height=720&fps=30&fourcc=MJPG"))
    assert p == {
        "node": "/dev/video2",
        "width": 1280,
        "height": 720,
        "fps": 30.0,
        "fourcc": "MJPG",
        "buffers": 64,
    }
    for bad, match in [
        ("v4l2://dev/video0", "three slashes"),
        ("v4l2:///dev/video0?fourcc=MJPEG", "fourcc"),
        ("v4l2:///dev/video0?gain=3", "unknown parameter"),
        ("v4l2:///dev/video0?width=-1", ">= 0"),
    ]:
        with pytest.raises(ConfigError, match=match):
            parse_v4l2_spec(DeviceSpec.parse(bad))


def test_free_running_frames_with_host_time_and_software_sync() -> None:
    cap = FakeCapture()
    cam = V4l2Camera(DeviceSpec.parse("v4l2:///dev/video9?width=64&height=48"), capture=cap)
    assert cam.info.facts["sync"] == "software"
    assert Capability.FREE_RUN in cam.capabilities
    assert Capability.HARDWARE_TRIGGER not in cam.capabilities
    assert Capability.SOFTWARE_SYNC in cam.capabilities
    assert cam.required_capabilities(CameraSettings(trigger_mode="hardware")) - cam.capabilities == {
        Capability.HARDWARE_TRIGGER
    }
    with pytest.raises(ConfigError, match="needs a trigger input"):
        cam.configure(CameraSettings(trigger_mode="hardware"))
    cam.configure(CameraSettings(trigger_mode="free_run", exposure_us=5000))
    assert cap.props[cv2.CAP_PROP_EXPOSURE] == 50  # UVC units of 100 us
    assert cam.frame_shape == (48, 64, 3)
    cam.start()
    with pytest.raises(DeviceError, match="stop"):
        cam.configure(CameraSettings(trigger_mode="free_run"))
    frames = [cam.read_frame(1.0) for _ in range(5)]
    cam.stop()
    assert all(f is not None for f in frames)
    counters = [f.frame_counter for f in frames if f is not None]
    assert counters == list(range(5))
    f0 = frames[0]
    assert f0 is not None
    assert f0.image.shape == (48, 64, 3)
    assert f0.image[1, 1].tolist() == [0, 0, 255]  # BGR blue became RGB blue
    assert f0.t_exposure_start_us == f0.host_time_ns // 1000 - 5000
    hosts = [f.host_time_ns for f in frames if f is not None]
    assert hosts == sorted(hosts)
    assert cam.stats().delivered >= 5
    cam.close()
    cam.close()
    assert cap.released


@pytest.mark.slow
def test_mono_and_unplug_is_reported() -> None:
    cap = FakeCapture()
    cam = V4l2Camera(DeviceSpec.parse("v4l2:///dev/video9"), capture=cap)
    cam.configure(CameraSettings(trigger_mode="free_run", pixel_format="mono8"))
    assert cam.frame_shape == (48, 64)
    cam.start()
    f = cam.read_frame(1.0)
    assert f is not None
    assert f.image.shape == (48, 64)
    cap.plugged = False
    with pytest.raises(DeviceError, match="unplugged"):  # noqa: PT012
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            cam.read_frame(0.2)
    cam.close()


def test_bayer_rg8_is_refused_clearly() -> None:
    cam = V4l2Camera(DeviceSpec.parse("v4l2:///dev/video9"), capture=FakeCapture())
    try:
        with pytest.raises(ConfigError, match=r"/dev/video9: pixel_format 'bayer_rg8' cannot be delivered"):
            cam.configure(CameraSettings(trigger_mode="free_run", pixel_format="bayer_rg8"))
    finally:
        cam.close()


def test_unopenable_node_names_it() -> None:
    with pytest.raises(DeviceError, match="/dev/video-nope-rigd"):
        open_v4l2_camera(DeviceSpec.parse("v4l2:///dev/video-nope-rigd"))


@pytest.mark.skipif(
    not glob.glob("/dev/video*"), reason="no /dev/video* node on this machine (no UVC camera)"
)
def test_real_v4l2_node_free_runs() -> None:
    node = sorted(glob.glob("/dev/video*"))[0]
    cam = open_v4l2_camera(DeviceSpec.parse(f"v4l2://{node}"))
    try:
        cam.configure(CameraSettings(trigger_mode="free_run"))
        cam.start()
        f = cam.read_frame(3.0)
        cam.stop()
        assert f is not None
        assert f.image.shape == cam.frame_shape
    finally:
        cam.close()


@pytest.mark.slow
def test_free_running_camera_in_a_capture_is_synchronized_by_host_time(tmp_path: Path) -> None:
    """A V4L2 camera in a rig: frames land in rig time through the host clock, each goes to
    the nearest pulse, and the take says its sync is software-only."""
    import uuid

    from drivers.registry import register_backend
    from rigd.app.capture import run_capture
    from rigd.app.config import CameraConfig, default_sim_rig
    from rigd.take.reader import Take

    class PacedCapture(FakeCapture):
        def read(self) -> tuple[bool, np.ndarray | None]:
            time.sleep(0.04)  # ~25 FPS, free running
            return super().read()

    register_backend(
        "rgb_camera",
        "fakev4l2",
        lambda spec: V4l2Camera(DeviceSpec.parse("v4l2:///dev/video9"), capture=PacedCapture()),
    )
    cfg = default_sim_rig(world=f"sw-{uuid.uuid4().hex[:8]}", resolution=(160, 90), pixel_format="mono8")
    cfg.cameras = [cfg.cameras[0], CameraConfig(name="uvc", spec="fakev4l2://x")]
    cfg.cameras[1].settings.trigger_mode = "free_run"
    res = run_capture(cfg, tmp_path, 1.5)
    dev = res.report.devices["uvc"]
    assert dev.sync == "software"
    assert dev.clock_from == "host"
    assert dev.n_matched > 20
    assert dev.residual_max_us <= 1e6 / 30 / 2  # nearest pulse, within half a period
    assert res.report.devices["cam0"].sync == "hardware"
    with Take(res.path) as take:
        uvc = take.camera("uvc")
        assert len(uvc) > 20
        first, last = take.pulses().t_us[[0, -1]]
        t = uvc.timestamps_us
        assert (np.diff(t) > 0).all()
        # In rig time (host monotonic time would be ~1e12 us); a free-running camera also
        # delivers frames during the drain after the last pulse.
        assert first - 300_000 < t[0]
        assert t[-1] < last + 2_000_000
        assert any("free-running" in w for w in res.report.warnings)


@pytest.mark.slow
def test_camera_unplugged_mid_take_is_reported_and_the_take_goes_on(tmp_path: Path) -> None:
    import threading
    import uuid

    from drivers.registry import register_backend
    from rigd.app.capture import run_capture
    from rigd.app.config import CameraConfig, default_sim_rig

    cap = FakeCapture()

    def factory(spec: DeviceSpec) -> V4l2Camera:
        if not cap.plugged:  # what opening a vanished /dev/video node does
            raise DeviceError("V4L2 camera /dev/video9: no such device")
        return V4l2Camera(DeviceSpec.parse("v4l2:///dev/video9"), capture=cap)

    register_backend("rgb_camera", "unplugv4l2", factory)
    cfg = default_sim_rig(world=f"up-{uuid.uuid4().hex[:8]}", resolution=(160, 90), pixel_format="mono8")
    cfg.cameras = [cfg.cameras[0], CameraConfig(name="uvc", spec="unplugv4l2://x")]
    cfg.cameras[1].settings.trigger_mode = "free_run"
    threading.Timer(1.0, lambda: setattr(cap, "plugged", False)).start()
    res = run_capture(cfg, tmp_path, 2.0)
    assert res.frames["cam0"] == 60  # the other devices kept going
    assert res.events["ev0"] > 0
    assert res.frames["uvc"] > 0
    assert any(loss.device == "uvc" and "failed mid-take" in loss.reason for loss in res.report.losses)
    assert any("uvc failed mid-take" in w for w in res.report.warnings)
    assert any("did not come back" in loss.reason for loss in res.report.losses)  # reconnects were tried
