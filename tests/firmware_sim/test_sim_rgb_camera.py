"""The simulated camera: one frame per rising edge, exact device stamps, honest losses."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from uuid import uuid4

import numpy as np
import pytest

from drivers.base import Capability
from drivers.registry import DeviceSpec
from firmware_sim.rgb_camera import SimRgbCamera, open_sim_camera
from firmware_sim.testing.wire import fire_pulses
from firmware_sim.world import Edge, SimWorld, get_world, reset_world
from rigd.core.errors import ConfigError, DeviceError
from rigd.core.frames import Frame
from rigd.core.pixels import mosaic_rggb
from rigd.core.settings import CameraSettings


def fire_in_thread(world: SimWorld, n: int, rate_hz: float = 100.0) -> tuple[threading.Thread, list[float]]:
    out: list[float] = []
    th = threading.Thread(target=lambda: out.extend(fire_pulses(world, n, rate_hz)), daemon=True)
    th.start()
    return th, out


def read_all(cam: SimRgbCamera, expected: int, timeout_s: float = 3.0) -> list[Frame]:
    frames: list[Frame] = []
    while len(frames) < expected:
        f = cam.read_frame(timeout_s)
        if f is None:
            break
        frames.append(f)
    return frames


@pytest.fixture
def world_name() -> Iterator[str]:
    name = f"t-{uuid4().hex}"
    yield name
    reset_world(name)


def open_cam(world: str, name: str = "cam0", extra: str = "") -> SimRgbCamera:
    """A sim camera; `extra` ("&k=v...") adds parameters or replaces the defaults (a spec that
    gives one twice is refused)."""
    params = {"offset_us": "1503311", "drift_ppm": "80", "width": "320", "height": "180"}
    for kv in filter(None, extra.split("&")):
        key, value = kv.split("=", 1)
        params[key] = value
    query = "&".join(f"{k}={v}" for k, v in params.items())
    return open_sim_camera(DeviceSpec.parse(f"sim://{world}/{name}?{query}"))


def test_one_frame_per_rising_edge_with_exact_device_stamps(world_name: str) -> None:
    with open_cam(world_name) as cam:
        cam.configure(CameraSettings(exposure_us=2000))
        cam.start()
        times = fire_pulses(get_world(world_name), 12, rate_hz=150)
        frames = read_all(cam, 12)
        cam.stop()
        assert cam.read_frame(0.2) is None  # exactly one per edge, falling edges expose nothing
        assert [f.frame_counter for f in frames] == list(range(12))
        assert [f.t_exposure_start_us for f in frames] == [cam.clock.stamp(t) for t in times]
        assert all(f.exposure_us == 2000 for f in frames)
        assert all(f.shape == (180, 320, 3) and f.image.dtype == np.uint8 for f in frames)
        hosts = [f.host_time_ns for f in frames]
        assert hosts == sorted(hosts)
        # The scene moves between frames.
        assert np.abs(frames[0].image.astype(int) - frames[-1].image.astype(int)).max() > 30
        st = cam.stats()
        assert st.delivered == 12
        assert st.device_dropped == 0
        truth = get_world(world_name).truth
        assert truth.frames["cam0"] == [(i, t, True) for i, t in enumerate(times)]
        assert truth.clocks["cam0"] is cam.clock


def test_edges_while_stopped_expose_nothing_and_counter_restarts(world_name: str) -> None:
    world = get_world(world_name)
    with open_cam(world_name) as cam:
        fire_pulses(world, 3)
        assert cam.read_frame(0.1) is None
        cam.start()
        fire_pulses(world, 2)
        cam.stop()
        fire_pulses(world, 2)
        assert [f.frame_counter for f in read_all(cam, 5, 0.3)] == [0, 1]
        cam.start()
        fire_pulses(world, 1)
        cam.stop()
        assert [f.frame_counter for f in read_all(cam, 5, 0.3)] == [0]


def test_drop_frames_fault_leaves_counter_gaps_and_truth(world_name: str) -> None:
    with open_cam(world_name, extra="&drop_frames=3,7") as cam:
        cam.configure(CameraSettings(exposure_us=1000))
        cam.start()
        fire_pulses(get_world(world_name), 10, rate_hz=200)
        cam.stop()
        counters = [f.frame_counter for f in read_all(cam, 10, 0.5)]
        assert counters == [0, 1, 2, 4, 5, 6, 8, 9]
        st = cam.stats()
        assert st.device_dropped == 2
        assert st.extra["transport_dropped"] == 2
        lost = [c for c, _, ok in get_world(world_name).truth.frames["cam0"] if not ok]
        assert lost == [3, 7]


def test_buffer_overflow_is_counted(world_name: str) -> None:
    with open_cam(world_name, extra="&buffer_frames=4") as cam:
        cam.configure(CameraSettings(exposure_us=500))
        cam.start()
        fire_pulses(get_world(world_name), 10, rate_hz=200)
        cam.stop()
        frames = read_all(cam, 10, 0.3)
        assert [f.frame_counter for f in frames] == [0, 1, 2, 3]
        st = cam.stats()
        assert st.device_dropped == 6
        assert st.extra["buffer_overflow"] == 6
        truth = get_world(world_name).truth.frames["cam0"]
        assert sum(not ok for _, _, ok in truth) == 6


@pytest.mark.parametrize(("fmt", "shape"), [("mono8", (180, 320)), ("rgb8", (180, 320, 3))])
def test_pixel_formats(world_name: str, fmt: str, shape: tuple[int, ...]) -> None:
    with open_cam(world_name, extra=f"&format={fmt}") as cam:
        assert cam.frame_shape == shape
        cam.start()
        fire_pulses(get_world(world_name), 1)
        f = cam.read_frame(2.0)
        assert f is not None
        assert f.shape == shape
        assert f.image.dtype == cam.frame_dtype
        other = "rgb8" if fmt == "mono8" else "mono8"
        cam.stop()
        cam.configure(CameraSettings(pixel_format=other))
        assert len(cam.frame_shape) == (3 if other == "rgb8" else 2)


@pytest.mark.parametrize("how", ["spec", "settings"])
def test_bayer_rg8_is_the_rggb_mosaic_of_the_rgb_render(world_name: str, how: str) -> None:
    extra = "&format=bayer_rg8" if how == "spec" else ""
    with open_cam(world_name, extra=extra) as cam:
        fmt = None if how == "spec" else "bayer_rg8"
        cam.configure(CameraSettings(exposure_us=8000, pixel_format=fmt))  # nominal: no gain applied
        assert cam.pixel_format == "bayer_rg8"
        assert cam.frame_shape == (180, 320)
        cam.start()
        fire_pulses(get_world(world_name), 1)
        f = cam.read_frame(2.0)
        cam.stop()
        assert f is not None
        assert f.image.shape == (180, 320)
        assert f.image.dtype == np.uint8
        assert f.pixel_format == "bayer_rg8"
        ((_, true_us, delivered),) = get_world(world_name).truth.frames["cam0"]
        assert delivered
        rgb = cam._scene.render(cam._view, true_us + 4000)
        np.testing.assert_array_equal(f.image, mosaic_rggb(rgb))


def test_free_run_uses_the_camera_clock(world_name: str) -> None:
    with open_cam(world_name, extra="&drift_ppm=100") as cam:
        cam.configure(CameraSettings(trigger_mode="free_run", free_run_fps=100.0, exposure_us=1000))
        get_world(world_name).wire.fire(Edge(True, get_world(world_name).now_us(), 0))  # ignored
        cam.start()
        frames = read_all(cam, 8)
        cam.stop()
        stamps = np.array([f.t_exposure_start_us for f in frames[:8]])
        assert [f.frame_counter for f in frames[:8]] == list(range(8))
        assert np.abs(np.diff(stamps) - 10_000).max() <= 1


def test_configure_while_started_and_bad_specs(world_name: str) -> None:
    cam = open_cam(world_name)
    assert Capability.HARDWARE_TRIGGER in cam.capabilities
    assert cam.info.kind == "rgb_camera"
    cam.start()
    with pytest.raises(DeviceError):
        cam.configure(CameraSettings())
    with pytest.raises(DeviceError):
        cam.start()
    cam.close()
    cam.close()
    with pytest.raises(DeviceError):
        cam.read_frame(0.0)
    for bad, word in (
        ("format=bgr8", "format"),
        ("buffer_frames=0", "buffer_frames"),
        ("drop_frames=a", "drop_frames"),
        ("exposure=3", "exposure"),
        ("width=x", "width"),
    ):
        with pytest.raises(ConfigError, match=word):
            open_sim_camera(DeviceSpec.parse(f"sim://{world_name}/cam1?{bad}"))
    with pytest.raises(ConfigError, match="no device name"):
        open_sim_camera(DeviceSpec.parse(f"sim://{world_name}/"))
