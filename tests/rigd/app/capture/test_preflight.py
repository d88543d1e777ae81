"""The capture preflight: a rig whose devices cannot do what the config asks is refused up
front, in one line naming every such device, and nothing is created or left open."""

from __future__ import annotations

import json
import uuid
from pathlib import Path

import h5py
import pytest

from drivers.registry import DeviceSpec, register_backend
from drivers.testing.fake_capture import FakeCapture
from drivers.v4l2_camera import V4l2Camera
from rigd.app.capture import CaptureSession
from rigd.app.config import CameraConfig, default_sim_rig
from rigd.core.errors import ConfigError


def test_cameras_without_a_trigger_input_in_hardware_mode_are_refused_in_one_line(tmp_path: Path) -> None:
    opened: list[FakeCapture] = []

    def factory(spec: DeviceSpec) -> V4l2Camera:
        cap = FakeCapture()
        opened.append(cap)
        return V4l2Camera(DeviceSpec.parse("v4l2:///dev/video9"), capture=cap)

    register_backend("rgb_camera", "preflightv4l2", factory)
    cfg = default_sim_rig(world=f"pf-{uuid.uuid4().hex[:8]}", resolution=(160, 90), pixel_format="mono8")
    cfg.cameras = [
        cfg.cameras[0],
        CameraConfig(name="uvc1", spec="preflightv4l2://a"),  # trigger_mode defaults to hardware
        CameraConfig(name="uvc2", spec="preflightv4l2://b"),
    ]
    session = CaptureSession(cfg, tmp_path, duration_s=1.0)
    with pytest.raises(ConfigError) as err:
        session.start()
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith("not starting a take")
    assert "uvc1 (preflightv4l2://a) lacks hardware_trigger" in msg
    assert "uvc2 (preflightv4l2://b) lacks hardware_trigger" in msg
    assert "free_run" in msg  # says what to do instead
    assert "cam0" not in msg  # the sim camera can do what it is asked
    assert session.state == "failed"
    assert not list(tmp_path.glob("*.h5"))  # refused before a take file was created
    assert all(cap.released for cap in opened)  # and every opened device was closed


@pytest.mark.slow
def test_free_run_cameras_pass_and_are_recorded_as_software_synced(tmp_path: Path) -> None:
    register_backend(
        "rgb_camera",
        "preflightv4l2ok",
        lambda spec: V4l2Camera(DeviceSpec.parse("v4l2:///dev/video9"), capture=FakeCapture()),
    )
    cfg = default_sim_rig(world=f"pf-{uuid.uuid4().hex[:8]}", resolution=(160, 90), pixel_format="mono8")
    cfg.cameras = [cfg.cameras[0], CameraConfig(name="uvc", spec="preflightv4l2ok://x")]
    cfg.cameras[1].settings.trigger_mode = "free_run"
    session = CaptureSession(cfg, tmp_path, duration_s=0.3)
    session.start()
    session.request_stop("test")
    result = session.wait(60)
    assert result is not None
    with h5py.File(result.path) as f:
        sync = {k: json.loads(f[f"frames/{k}"].attrs["info_json"])["facts"]["sync"] for k in ("cam0", "uvc")}
    assert sync == {"cam0": "hardware", "uvc": "software"}  # what recovery reads back
