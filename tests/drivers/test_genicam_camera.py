"""The GenICam backend against Aravis' fake GigE Vision camera on loopback.

Needs Aravis 0.8 through PyGObject and `arv-fake-gv-camera-0.8` (Debian: gir1.2-aravis-0.8,
aravis-tools; pip: PyGObject). The fake camera cannot see a hardware line, so the rig's
trigger pulse is TriggerSoftware here (`trigger_source=Software`): the hardware-trigger code
path (TriggerSelector/Mode/Source/Activation, one buffer per trigger) is the same.
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
from collections.abc import Callable, Iterator

import pytest

from drivers.base import RgbCamera
from drivers.registry import DeviceSpec
from rigd.core.errors import BackendUnavailableError, ConfigError, DeviceError
from rigd.core.settings import CameraSettings
from tests.contracts.camera_contract import RgbCameraContract, read_n

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
pytestmark = pytest.mark.skipif(_REASON is not None, reason=f"Aravis fake camera unavailable: {_REASON}")


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


class TestGenicamFakeCamera(RgbCameraContract):
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
            if not camera._running:  # type: ignore[attr-defined]
                return
            _trigger(camera, n)

        return fire


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


def test_gige_block_id_wrap_keeps_the_counter_increasing(fake_camera: None) -> None:
    from drivers.genicam_camera import GenicamCamera

    cam = _open()
    try:
        assert isinstance(cam, GenicamCamera)
        assert [cam._unwrap(i) for i in (65534, 65535, 1, 2)] == [65534, 65535, 65536, 65537]
    finally:
        cam.close()


def test_errors_name_the_camera(fake_camera: None) -> None:
    with pytest.raises(DeviceError, match="no GenICam camera 'NOPE'"):
        _open("genicam://NOPE")
    with pytest.raises(ConfigError, match="unknown parameter"):
        _open("genicam://127.0.0.1?exposure=5")
    with pytest.raises(ConfigError, match="roi must be"):
        _open("genicam://127.0.0.1?interface=127.0.0.1&roi=1,2,3")
    cam = _open()
    try:
        with pytest.raises(ConfigError, match="exposure"):
            cam.configure(CameraSettings(exposure_us=10**9))
    finally:
        cam.close()
