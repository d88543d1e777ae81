"""`file://` replay of a video or an image folder as an RGB camera: the free-run camera
contract on both, exact pixels from PNG folders, timestamps from the container, from fps and
from timestamps.txt, looping, pacing (lower bounds only) and every bad input in one line."""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.base import Capability, RgbCamera
from drivers.file_camera import FileCamera, natural_key
from drivers.registry import DeviceSpec, check_spec, open_device
from drivers.testing.camera import FreeRunCameraContract
from rigd.core.errors import ConfigError, DeviceError
from rigd.core.frames import Frame
from rigd.core.settings import CameraSettings

W, H = 32, 24


def _images(n: int, *, seed: int = 0, mono: bool = False) -> list[np.ndarray]:
    """n random BGR (or gray) images with the index in pixel (0, 0)."""
    rng = np.random.default_rng(seed)
    shape = (H, W) if mono else (H, W, 3)
    out = []
    for i in range(n):
        img = rng.integers(0, 256, shape, dtype=np.uint8)
        img[0, 0] = i
        out.append(img)
    return out


def _folder(tmp_path: Path, n: int = 10, *, mono: bool = False, name: str = "frames") -> Path:
    folder = tmp_path / name
    folder.mkdir()
    for i, img in enumerate(_images(n, mono=mono)):
        assert cv2.imwrite(str(folder / f"f{i}.png"), img)
    return folder


def _video(tmp_path: Path, n: int = 10, fps: float = 25.0) -> Path:
    path = tmp_path / "clip.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"mp4v"), fps, (W, H))
    assert writer.isOpened()
    for i in range(n):
        writer.write(np.full((H, W, 3), (i * 20, 100, 200 - i * 10), np.uint8))
    writer.release()
    return path


def _all(camera: RgbCamera, settings: CameraSettings | None = None, limit: int = 1000) -> list[Frame]:
    """Start the camera and read until the recording ends (or `limit` frames)."""
    camera.configure(settings or CameraSettings(trigger_mode="free_run"))
    camera.start()
    frames: list[Frame] = []
    while len(frames) < limit and (f := camera.read_frame(5.0)) is not None:
        frames.append(f)
    camera.stop()
    return frames


# -- the contract on both kinds of input ---------------------------------------------------
class _FileContract(FreeRunCameraContract):
    # A recording's exposure is its own: the suite asks for the default, not EXPOSURE_CONTROL.
    settings = CameraSettings(trigger_mode="free_run", free_run_fps=50.0)


class TestVideoContract(_FileContract):
    @pytest.fixture
    def camera(self, tmp_path: Path) -> Iterator[RgbCamera]:
        cam = open_device("rgb_camera", f"file://{_video(tmp_path, 12)}?pace=0")
        yield cam
        cam.close()


class TestFolderContract(_FileContract):
    @pytest.fixture
    def camera(self, tmp_path: Path) -> Iterator[RgbCamera]:
        cam = open_device("rgb_camera", f"file://{_folder(tmp_path, 12)}/?pace=0&buffers=4")
        yield cam
        cam.close()


class TestPacedFolderContract(_FileContract):
    """Real-time pacing (at 1000 fps): the contract holds while frames wait for their time."""

    @pytest.fixture
    def camera(self, tmp_path: Path) -> Iterator[RgbCamera]:
        cam = open_device("rgb_camera", f"file://{_folder(tmp_path, 40)}?fps=1000&loop=1")
        yield cam
        cam.close()


# -- what the camera says about itself -----------------------------------------------------
def test_capabilities_are_honest_and_hardware_mode_is_refused(tmp_path: Path) -> None:
    cam = open_device("rgb_camera", f"file://{_folder(tmp_path, 3)}?pace=0")
    caps = cam.capabilities
    assert Capability.HARDWARE_TRIGGER not in caps
    assert {Capability.SOFTWARE_SYNC, Capability.DEVICE_TIMESTAMPS, Capability.FREE_RUN} <= caps
    assert Capability.EXPOSURE_CONTROL not in caps
    hardware = CameraSettings(trigger_mode="hardware")
    assert cam.required_capabilities(hardware) - caps == {Capability.HARDWARE_TRIGGER}
    with pytest.raises(ConfigError, match="hardware_trigger: trigger_mode 'hardware' needs a trigger input"):
        cam.configure(hardware)
    assert cam.info.facts["sync"] == "software"
    assert cam.info.vendor == "file"
    cam.close()


def test_the_capture_preflight_refuses_hardware_mode_in_one_line(tmp_path: Path) -> None:
    from rigd.app.capture.preflight import check_rig

    spec = f"file://{_folder(tmp_path, 3)}"
    cam = open_device("rgb_camera", spec)
    wanted = cam.required_capabilities(CameraSettings(trigger_mode="hardware"))
    with pytest.raises(ConfigError) as err:
        check_rig([("cam1", spec, cam, wanted)])
    msg = str(err.value)
    assert "\n" not in msg
    assert f"cam1 ({spec}) lacks hardware_trigger" in msg
    check_rig([("cam1", spec, cam, cam.required_capabilities(CameraSettings(trigger_mode="free_run")))])
    cam.close()


def test_file_specs_dispatch_by_device_kind(tmp_path: Path) -> None:
    folder = _folder(tmp_path, 2)
    check_spec("rgb_camera", f"file://{folder}")
    check_spec("event_sensor", "file:///abs/rec.raw")
    cam = open_device("rgb_camera", f"file://{folder}/")
    assert isinstance(cam, FileCamera)
    cam.close()
    with pytest.raises(ConfigError, match="unknown parameter"):
        open_device("rgb_camera", f"file://{folder}?chunk_bytes=4096")
    # the same scheme as an event sensor is still the RAW/DAT replay, which refuses a folder
    with pytest.raises(ConfigError, match="is a directory, not a RAW or DAT recording"):
        open_device("event_sensor", f"file://{folder}")


# -- pixels --------------------------------------------------------------------------------
def test_png_folder_round_trips_pixels_exactly(tmp_path: Path) -> None:
    folder = _folder(tmp_path, 5)
    expected = _images(5)
    cam = open_device("rgb_camera", f"file://{folder}?pace=0")
    assert cam.frame_shape == (H, W, 3)
    frames = _all(cam, CameraSettings(trigger_mode="free_run", pixel_format="rgb8"))
    assert len(frames) == 5
    for f, bgr in zip(frames, expected, strict=True):
        assert f.image.dtype == np.uint8
        np.testing.assert_array_equal(f.image, bgr[:, :, ::-1])  # BGR on disk -> RGB
    mono = _all(cam, CameraSettings(trigger_mode="free_run", pixel_format="mono8"))
    assert cam.frame_shape == (H, W)
    for f, bgr in zip(mono, expected, strict=True):
        np.testing.assert_array_equal(f.image, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    with pytest.raises(ConfigError, match="'bayer_rg8' cannot be delivered"):
        cam.configure(CameraSettings(trigger_mode="free_run", pixel_format="bayer_rg8"))
    cam.close()


def test_gray_png_folder_defaults_to_mono8_exactly(tmp_path: Path) -> None:
    folder = _folder(tmp_path, 4, mono=True)
    cam = open_device("rgb_camera", f"file://{folder}?pace=0")
    assert cam.frame_shape == (H, W)
    frames = _all(cam)
    for f, gray in zip(frames, _images(4, mono=True), strict=True):
        np.testing.assert_array_equal(f.image, gray)
    rgb = _all(cam, CameraSettings(trigger_mode="free_run", pixel_format="rgb8"))
    np.testing.assert_array_equal(rgb[1].image, np.repeat(_images(4, mono=True)[1][:, :, None], 3, axis=2))
    cam.close()


def test_video_frames_are_rgb(tmp_path: Path) -> None:
    cam = open_device("rgb_camera", f"file://{_video(tmp_path, 10)}?pace=0")
    frames = _all(cam)
    assert len(frames) == 10
    assert all(f.image.shape == (H, W, 3) for f in frames)
    # frame 0 was written as BGR (0, 100, 200): lossy codec, but red stays the largest channel
    r, g, b = frames[0].image[H // 2, W // 2].astype(int)
    assert r > g > b
    assert abs(r - 200) < 20
    assert b < 20
    cam.close()


def test_folders_sort_naturally() -> None:
    names = ["f10.png", "f2.png", "f1.png", "F3.png"]
    assert sorted(names, key=natural_key) == ["f1.png", "f2.png", "F3.png", "f10.png"]


def test_folder_replays_in_natural_order(tmp_path: Path) -> None:
    folder = _folder(tmp_path, 12)  # f0 .. f11: plain sorting would put f10 after f1
    frames = _all(open_device("rgb_camera", f"file://{folder}?pace=0"))
    assert [int(f.image[0, 0, 0]) for f in frames] == list(range(12))  # index in pixel (0, 0)


# -- timestamps ----------------------------------------------------------------------------
def test_video_timestamps_from_the_container(tmp_path: Path) -> None:
    cam = open_device("rgb_camera", f"file://{_video(tmp_path, 10, fps=25.0)}?pace=0")
    frames = _all(cam)
    assert [f.t_exposure_start_us for f in frames] == [i * 40_000 for i in range(10)]
    assert [f.frame_counter for f in frames] == list(range(10))
    assert cam.stats().delivered == 10
    assert cam.stats().extra["frames_in_file"] == 10
    assert "container" in cam.info.facts["timestamps"]
    cam.close()


def test_video_fps_param_overrides_the_container(tmp_path: Path) -> None:
    cam = open_device("rgb_camera", f"file://{_video(tmp_path, 4, fps=25.0)}?pace=0&fps=100")
    assert [f.t_exposure_start_us for f in _all(cam)] == [0, 10_000, 20_000, 30_000]
    cam.close()


class _NoTimesCapture:
    """A capture whose container reports no frame times (POS_MSEC stays 0)."""

    def __init__(self, real: object) -> None:
        self._real = real

    def __getattr__(self, name: str) -> object:
        return getattr(self._real, name)

    def get(self, prop: int) -> float:
        if prop == cv2.CAP_PROP_POS_MSEC:
            return 0.0
        return float(self._real.get(prop))  # type: ignore[attr-defined]


class _Cv2NoTimes:
    """OpenCV whose captures report no frame times."""

    def __getattr__(self, name: str) -> object:
        return getattr(cv2, name)

    def VideoCapture(self, path: str) -> _NoTimesCapture:  # noqa: N802 - OpenCV's name
        return _NoTimesCapture(cv2.VideoCapture(path))


def test_video_without_container_times_falls_back_to_index_over_fps(tmp_path: Path) -> None:
    cam = FileCamera(_video(tmp_path, 5, fps=25.0), pace=0, cv2_module=_Cv2NoTimes())
    assert [f.t_exposure_start_us for f in _all(cam)] == [0, 40_000, 80_000, 120_000, 160_000]
    cam.close()


def test_folder_timestamps_from_fps(tmp_path: Path) -> None:
    folder = _folder(tmp_path, 4)
    default = _all(open_device("rgb_camera", f"file://{folder}?pace=0"))
    assert [f.t_exposure_start_us for f in default] == [0, 33_333, 66_667, 100_000]  # 30 fps
    ten = _all(open_device("rgb_camera", f"file://{folder}?pace=0&fps=10"))
    assert [f.t_exposure_start_us for f in ten] == [0, 100_000, 200_000, 300_000]


def test_folder_timestamps_from_timestamps_txt(tmp_path: Path) -> None:
    folder = _folder(tmp_path, 4)
    (folder / "timestamps.txt").write_text("1000\n1500\n\n9000\n12345\n")
    cam = open_device("rgb_camera", f"file://{folder}?pace=0")
    frames = _all(cam)
    assert [f.t_exposure_start_us for f in frames] == [1000, 1500, 9000, 12345]
    assert [f.frame_counter for f in frames] == [0, 1, 2, 3]
    assert cam.info.facts["timestamps"] == "timestamps.txt"
    cam.close()


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("1000\n2000\n3000\n", r"timestamps.txt: 3 timestamps for 4 images"),
        ("1\n2\n3\n4\n5\n", r"timestamps.txt: 5 timestamps for 4 images"),
        ("1000\n2000\n2000\n4000\n", r"timestamps.txt line 3: 2000 is not after 2000 on line 2"),
        ("1000\n500\n2000\n4000\n", r"timestamps.txt line 2: 500 is not after 1000 on line 1"),
        ("1000\n2000\n3.5\n4000\n", r"timestamps.txt line 3: '3.5' is not an integer"),
    ],
)
def test_bad_timestamps_txt_names_file_and_line(tmp_path: Path, text: str, match: str) -> None:
    folder = _folder(tmp_path, 4)
    (folder / "timestamps.txt").write_text(text)
    with pytest.raises(ConfigError, match=match) as err:
        open_device("rgb_camera", f"file://{folder}")
    assert str(folder / "timestamps.txt") in str(err.value)
    assert "\n" not in str(err.value)


# -- loop, end, restart --------------------------------------------------------------------
def test_loop_keeps_counters_and_timestamps_increasing(tmp_path: Path) -> None:
    cam = open_device("rgb_camera", f"file://{_folder(tmp_path, 3)}?pace=0&fps=10&loop=1")
    frames = _all(cam, limit=8)
    assert [f.frame_counter for f in frames] == list(range(8))
    # span 200 ms + one period: each pass starts 300 ms after the last
    assert [f.t_exposure_start_us for f in frames] == [i * 100_000 for i in range(8)]
    assert [int(f.image[0, 0, 0]) for f in frames] == [0, 1, 2, 0, 1, 2, 0, 1]  # index in pixel (0, 0)
    assert cam.stats().extra["passes"] >= 3
    cam.close()


def test_loop_over_timestamps_txt_and_video(tmp_path: Path) -> None:
    folder = _folder(tmp_path, 3)
    (folder / "timestamps.txt").write_text("100\n200\n400\n")
    frames = _all(open_device("rgb_camera", f"file://{folder}?pace=0&loop=1"), limit=7)
    # span 300 + period 150 (the mean) = 450 per pass
    assert [f.t_exposure_start_us for f in frames] == [100, 200, 400, 550, 650, 850, 1000]
    video = _all(open_device("rgb_camera", f"file://{_video(tmp_path, 4, fps=25)}?pace=0&loop=1"), limit=9)
    assert [f.t_exposure_start_us for f in video] == [i * 40_000 for i in range(9)]
    assert [f.frame_counter for f in video] == list(range(9))


def test_end_of_recording_ends_acquisition_cleanly(tmp_path: Path) -> None:
    cam = open_device("rgb_camera", f"file://{_folder(tmp_path, 3)}?pace=0")
    cam.configure(CameraSettings(trigger_mode="free_run"))
    cam.start()
    assert len([cam.read_frame(5.0) for _ in range(3)]) == 3
    t = time.monotonic()
    assert cam.read_frame(5.0) is None  # the end: no waiting out the timeout
    assert time.monotonic() - t < 4.0
    assert cam.read_frame(0.0) is None
    assert cam.stats().delivered == 3
    assert cam.stats().device_dropped == 0
    cam.stop()
    # a new start replays from the first frame
    again = _all(cam)
    assert [f.frame_counter for f in again] == [0, 1, 2]
    assert [f.t_exposure_start_us for f in again] == [0, 33_333, 66_667]
    assert cam.stats().delivered == 6
    cam.close()


def test_a_slow_reader_loses_nothing(tmp_path: Path) -> None:
    cam = open_device("rgb_camera", f"file://{_folder(tmp_path, 12)}?pace=0&buffers=2")
    frames = _all(cam)
    assert [f.frame_counter for f in frames] == list(range(12))
    assert cam.stats().extra["host_queue_dropped"] == 0
    cam.close()


def test_pacing_never_delivers_a_frame_early(tmp_path: Path) -> None:
    """pace=1 at 50 fps: frame i is handed over no earlier than i * 20 ms after start()
    (a lower bound only: a busy machine may deliver late, never early)."""
    cam = open_device("rgb_camera", f"file://{_folder(tmp_path, 6)}?fps=50")
    t_start = time.monotonic_ns()
    hosts = [f.host_time_ns for f in _all(cam)]
    assert len(hosts) == 6
    for i, h in enumerate(hosts):
        assert h - t_start >= i * 20_000_000
    half = open_device("rgb_camera", f"file://{_folder(tmp_path, 3, name='b')}?fps=50&pace=0.5")
    t_start = time.monotonic_ns()
    hosts = [f.host_time_ns for f in _all(half)]
    assert hosts[2] - t_start >= 80_000_000  # 40 ms of recording at half speed
    cam.close()
    half.close()


# -- bad input -----------------------------------------------------------------------------
def test_missing_path_names_it(tmp_path: Path) -> None:
    missing = tmp_path / "nope.mp4"
    with pytest.raises(ConfigError, match=re.escape(f"{missing}: no such file or folder")):
        open_device("rgb_camera", f"file://{missing}")
    with pytest.raises(ConfigError, match="no file or folder path"):
        open_device("rgb_camera", "file://")


def test_unreadable_video_names_it(tmp_path: Path) -> None:
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"not a video " * 100)
    with pytest.raises(ConfigError, match=re.escape(f"video {bad}: OpenCV cannot open it")) as err:
        open_device("rgb_camera", f"file://{bad}")
    assert "\n" not in str(err.value)
    empty = tmp_path / "empty.avi"
    empty.write_bytes(b"")
    with pytest.raises(ConfigError, match=re.escape(str(empty))):
        open_device("rgb_camera", f"file://{empty}")


def test_single_image_points_to_its_folder(tmp_path: Path) -> None:
    folder = _folder(tmp_path, 2)
    with pytest.raises(ConfigError, match="a single image, not a video"):
        open_device("rgb_camera", f"file://{folder / 'f0.png'}")


def test_empty_folder_names_it(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("no images here")
    with pytest.raises(ConfigError, match=re.escape(f"image folder {tmp_path} holds no images")):
        open_device("rgb_camera", f"file://{tmp_path}/")


def test_mixed_sizes_name_the_first_file_that_differs(tmp_path: Path) -> None:
    folder = _folder(tmp_path, 4)
    cv2.imwrite(str(folder / "f2.png"), np.zeros((H + 1, W, 3), np.uint8))
    cv2.imwrite(str(folder / "f3.jpg"), np.zeros((H, W + 2, 3), np.uint8))
    with pytest.raises(
        ConfigError, match=re.escape(f"image folder {folder}: f2.png is 32x25, not 32x24 like f0.png")
    ):
        open_device("rgb_camera", f"file://{folder}")
    (folder / "f2.png").unlink()
    with pytest.raises(ConfigError, match=r"f3\.jpg is 34x24, not 32x24"):  # a JPEG's header, read alone
        open_device("rgb_camera", f"file://{folder}")


def test_undecodable_images_are_named(tmp_path: Path) -> None:
    folder = _folder(tmp_path, 3)
    (folder / "f0.png").write_bytes(b"garbage")
    with pytest.raises(ConfigError, match=r"cannot decode f0\.png"):
        open_device("rgb_camera", f"file://{folder}")
    folder2 = _folder(tmp_path, 3, name="later")
    good = cv2.imread(str(folder2 / "f1.png"))
    assert good is not None
    # a header that says the right size over damaged data: found at replay, named to the reader
    (folder2 / "f1.png").write_bytes((folder2 / "f1.png").read_bytes()[:40])
    cam = open_device("rgb_camera", f"file://{folder2}?pace=0")
    cam.configure(CameraSettings(trigger_mode="free_run"))
    cam.start()
    assert cam.read_frame(5.0) is not None
    with pytest.raises(DeviceError, match=r"cannot decode f1\.png"):
        cam.read_frame(5.0)
    cam.close()


def test_bad_parameters_are_refused(tmp_path: Path) -> None:
    folder = _folder(tmp_path, 2)
    for query, match in [
        ("pace=-1", "pace must be >= 0"),
        ("fps=0", "fps must be > 0"),
        ("fps=abc", "is not a number"),
        ("buffers=0", "buffers must be >= 1"),
        ("loop=yes", "is not an integer"),
    ]:
        with pytest.raises(ConfigError, match=match):
            open_device("rgb_camera", f"file://{folder}?{query}")
    assert DeviceSpec.parse(f"file://{folder}?pace=0").params == {"pace": "0"}


@pytest.mark.slow
def test_a_replayed_camera_in_a_sim_rig_is_synchronized_by_host_time(tmp_path: Path) -> None:
    """A looping folder replay beside the simulated rig: the take holds its frames with the
    replay's counters, and says its sync is software-only."""
    import uuid

    from rigd.app.capture import run_capture
    from rigd.app.config import CameraConfig, default_sim_rig
    from rigd.take.reader import Take

    folder = _folder(tmp_path, 10)
    cfg = default_sim_rig(world=f"fc-{uuid.uuid4().hex[:8]}", resolution=(160, 90), pixel_format="mono8")
    cfg.cameras = [cfg.cameras[0], CameraConfig(name="replay", spec=f"file://{folder}?fps=25&loop=1")]
    cfg.cameras[1].settings.trigger_mode = "free_run"
    res = run_capture(cfg, tmp_path / "takes", 1.0)
    assert res.report.devices["replay"].sync == "software"
    assert res.frames["replay"] > 0
    with Take(res.path) as take:
        frames = take.camera("replay")
        assert len(frames) == res.frames["replay"]
        assert (np.diff(frames.timestamps_us) > 0).all()
