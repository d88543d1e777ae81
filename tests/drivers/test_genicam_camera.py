"""The GenICam backend: the camera contracts against a stand-in Aravis module (always), and
against Aravis' fake GigE Vision camera on loopback.

The loopback tests need Aravis 0.8 through PyGObject and `arv-fake-gv-camera-0.8` (Debian:
gir1.2-aravis-0.8, aravis-tools; pip: PyGObject) and skip, saying so, without them. The fake
camera cannot see a hardware line, so the rig's trigger pulse is TriggerSoftware there
(`trigger_source=Software`): the hardware-trigger code path (TriggerSelector/Mode/Source/
Activation, one buffer per trigger) is the same.
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
from collections.abc import Callable, Iterator

import pytest

from drivers.base import Capability, RgbCamera
from drivers.genicam_camera import GenicamCamera
from drivers.registry import DeviceSpec
from drivers.testing.camera import FreeRunCameraContract, HardwareTriggerCameraContract, read_n
from rigd.core.errors import BackendUnavailableError, ConfigError, DeviceError
from rigd.core.settings import CameraSettings
from tests.drivers.fake_aravis import FakeCamera, fake_aravis

FAKE = "arv-fake-gv-camera-0.8"
SPEC = "genicam://127.0.0.1?interface=127.0.0.1&trigger_source=Software&buffers=8"


def _aravis_reason() -> str | None:
    try:
        from drivers.genicam_camera import import_aravis

        import_aravis()
    except BackendUnavailableError as exc:
        return str(exc)
    if shutil.which(FAKE) is None:
        return f"{FAKE} not on PATH (apt-get install aravis-tools)"
    return None


_REASON = _aravis_reason()
needs_aravis = pytest.mark.skipif(_REASON is not None, reason=f"Aravis fake camera unavailable: {_REASON}")


# --- the contracts against the stand-in Aravis ---------------------------------------------


def _stand_in(fake: FakeCamera, query: str = "buffers=4") -> Iterator[RgbCamera]:
    cam = GenicamCamera(DeviceSpec.parse(f"genicam://RIGD01?{query}"), aravis=fake_aravis(fake))
    yield cam
    cam.close()


class TestGenicamStandIn(HardwareTriggerCameraContract):
    @pytest.fixture
    def fake(self) -> FakeCamera:
        return FakeCamera()

    @pytest.fixture
    def camera(self, fake: FakeCamera) -> Iterator[RgbCamera]:
        yield from _stand_in(fake)

    @pytest.fixture
    def pulse(self, fake: FakeCamera) -> Callable[[int], None]:
        def fire(n: int) -> None:
            for _ in range(n):
                fake.line_pulse()
                time.sleep(0.005)

        return fire


class TestGenicamStandInFreeRun(FreeRunCameraContract):
    @pytest.fixture
    def camera(self) -> Iterator[RgbCamera]:
        yield from _stand_in(FakeCamera(formats=("Mono8", "RGB8")))


def test_stand_in_capabilities_follow_the_camera() -> None:
    mono = GenicamCamera(DeviceSpec.parse("genicam://RIGD01"), aravis=fake_aravis(FakeCamera()))
    color = GenicamCamera(
        DeviceSpec.parse("genicam://RIGD01"), aravis=fake_aravis(FakeCamera(formats=("Mono8", "RGB8")))
    )
    try:
        assert Capability.COLOR not in mono.capabilities
        assert Capability.COLOR in color.capabilities
        assert Capability.HARDWARE_TRIGGER in mono.capabilities
        assert Capability.SOFTWARE_SYNC not in mono.capabilities
        with pytest.raises(ConfigError, match="color"):
            mono.configure(CameraSettings(pixel_format="rgb8"))
        color.configure(CameraSettings(pixel_format="rgb8", exposure_us=1000))
        assert color.frame_shape == (48, 64, 3)
    finally:
        mono.close()
        color.close()


def test_stand_in_bayer_rg8_maps_to_bayerrg8_or_is_refused() -> None:
    rgb_only = GenicamCamera(
        DeviceSpec.parse("genicam://RIGD01"), aravis=fake_aravis(FakeCamera(formats=("Mono8", "RGB8")))
    )
    fake = FakeCamera(formats=("BayerRG8", "Mono8"))
    bayer = GenicamCamera(DeviceSpec.parse("genicam://RIGD01"), aravis=fake_aravis(fake))
    try:
        with pytest.raises(ConfigError, match="BayerRG8 not offered"):
            rgb_only.configure(CameraSettings(pixel_format="bayer_rg8"))
        assert Capability.COLOR in bayer.capabilities  # a Bayer sensor is a colour camera
        assert bayer.pixel_format == "bayer_rg8"  # its default, though (H, W) like mono8
        bayer.configure(CameraSettings(pixel_format="mono8", exposure_us=1000))
        assert bayer.pixel_format == "mono8"
        bayer.configure(CameraSettings(pixel_format="bayer_rg8", exposure_us=1000))
        assert fake.pixel_format == "BayerRG8"
        assert bayer.frame_shape == (48, 64)
        bayer.start()
        fake.line_pulse()
        (frame,) = read_n(bayer, 1)
        bayer.stop()
        assert frame.image.shape == (48, 64)
        assert frame.pixel_format == "bayer_rg8"
        with pytest.raises(ConfigError, match="RGB8 not offered"):
            bayer.configure(CameraSettings(pixel_format="rgb8"))
    finally:
        rgb_only.close()
        bayer.close()


def test_stand_in_block_id_gaps_count_as_lost_frames() -> None:
    fake = FakeCamera()
    cam = GenicamCamera(DeviceSpec.parse("genicam://RIGD01?buffers=2"), aravis=fake_aravis(fake))
    try:
        cam.configure(CameraSettings(exposure_us=1000, pixel_format="mono8"))
        cam.start()
        fake.line_pulse()
        fake._frame_id += 2  # two frames lost between camera and host
        fake.line_pulse()
        frames = read_n(cam, 2)
        cam.stop()
        assert [f.frame_counter for f in frames] == [1, 4]
        st = cam.stats()
        assert (st.delivered, st.device_dropped, st.extra["frame_counter_gaps"]) == (2, 2, 2)
        assert st.extra["n_completed_buffers"] == 2
    finally:
        cam.close()


# --- Aravis' fake GigE Vision camera on loopback -------------------------------------------


def _gvcp_port_busy() -> bool:
    """Another fake camera (or a real one) already answers on 127.0.0.1:3956."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind(("127.0.0.1", 3956))
    except OSError:
        return True
    finally:
        s.close()
    return False


@pytest.fixture(scope="module")
def fake_camera() -> Iterator[None]:
    if _REASON is not None:
        pytest.skip(f"Aravis fake camera unavailable: {_REASON}")
    if _gvcp_port_busy():
        pytest.skip("UDP 127.0.0.1:3956 is taken: another GigE Vision (fake) camera runs on loopback")
    proc = subprocess.Popen(
        [FAKE, "-i", "lo", "-s", "RIGD01"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    time.sleep(0.5)
    if proc.poll() is not None:
        err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
        pytest.skip(f"{FAKE} -i lo exited at once (rc {proc.returncode}): {err[-300:]}")
    yield None
    proc.terminate()
    try:
        proc.wait(5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _trigger(camera: RgbCamera, n: int) -> None:
    """n software triggers at a rate the fake camera follows: it serves at most one trigger per
    frame period (and coalesces more), so wait for each buffer to complete before the next."""
    for _ in range(n):
        before = camera._stream_stats().get("n_completed_buffers", 0)  # type: ignore[attr-defined]
        camera.software_trigger()  # type: ignore[attr-defined]
        deadline = time.monotonic() + 1.0
        while camera._stream_stats().get("n_completed_buffers", 0) == before:  # type: ignore[attr-defined]
            if time.monotonic() > deadline:
                break
            time.sleep(0.005)
        time.sleep(0.01)


def _open(spec: str = SPEC) -> RgbCamera:
    from drivers.genicam_camera import open_genicam_camera

    return open_genicam_camera(DeviceSpec.parse(spec))


@needs_aravis
class TestGenicamFakeCamera(HardwareTriggerCameraContract):
    @pytest.fixture
    def camera(self, fake_camera: None) -> Iterator[RgbCamera]:
        cam = _open()
        cam.configure(CameraSettings(trigger_mode="hardware", exposure_us=1000, pixel_format="mono8"))
        yield cam
        cam.close()

    @pytest.fixture
    def pulse(self, camera: RgbCamera) -> Callable[[int], None]:
        def fire(n: int) -> None:
            # A pulse on a hardware line reaches nobody while the camera is not acquiring; the
            # fake camera would latch a software trigger and expose after start, so do not send it.
            if not camera.acquiring:
                return
            _trigger(camera, n)

        return fire


@needs_aravis
def test_info_facts_and_stream_statistics(fake_camera: None) -> None:
    cam = _open()
    try:
        assert cam.info.facts["sync"] == "hardware"
        assert cam.info.facts["transport"] == "GigEVision"
        assert cam.info.model
        cam.configure(CameraSettings(trigger_mode="hardware", exposure_us=2000, pixel_format="mono8"))
        cam.start()
        _trigger(cam, 3)
        frames = read_n(cam, 3)
        cam.stop()
        assert [f.exposure_us for f in frames] == [2000] * 3
        st = cam.stats()
        assert st.delivered == 3
        assert st.extra["n_completed_buffers"] == 3
        assert {"n_failures", "n_underruns", "n_missing_packets", "incomplete_buffers"} <= set(st.extra)
    finally:
        cam.close()


@needs_aravis
def test_roi_and_free_run(fake_camera: None) -> None:
    cam = _open(SPEC + "&roi=0,0,128,96")
    try:
        assert cam.frame_shape == (96, 128)
        cam.configure(CameraSettings(trigger_mode="free_run", free_run_fps=50.0, pixel_format="mono8"))
        cam.start()
        frames = read_n(cam, 3)
        cam.stop()
        assert len(frames) == 3
        assert all(f.shape == (96, 128) for f in frames)
    finally:
        cam.close()


@needs_aravis
def test_gige_block_id_wrap_keeps_the_counter_increasing(fake_camera: None) -> None:
    cam = _open()
    try:
        assert isinstance(cam, GenicamCamera)
        assert [cam._unwrap(i) for i in (65534, 65535, 1, 2)] == [65534, 65535, 65536, 65537]
    finally:
        cam.close()


@needs_aravis
def test_errors_name_the_camera(fake_camera: None) -> None:
    with pytest.raises(DeviceError, match="no GenICam camera 'NOPE'"):
        _open("genicam://NOPE")
    with pytest.raises(ConfigError, match="unknown parameter"):
        _open("genicam://127.0.0.1?exposure=5")
    with pytest.raises(ConfigError, match="roi must be"):
        _open("genicam://127.0.0.1?interface=127.0.0.1&roi=1,2,3")
    cam = _open()
    try:
        # Within the settings' own bounds (1 us..10 s) but below the fake camera's 10 us minimum.
        with pytest.raises(ConfigError, match="exposure 5 us outside"):
            cam.configure(CameraSettings(exposure_us=5))
    finally:
        cam.close()
