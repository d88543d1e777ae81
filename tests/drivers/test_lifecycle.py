"""The lifecycle the device base classes enforce, against a minimal grabbing camera, and the
capability rules (`required_capabilities`, configure's refusals)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from drivers.base import Capability, EventSensor, RgbCamera, Trigger, missing_capabilities
from drivers.lifecycle import END, Acquisition, DeliveryQueue, Signal
from drivers.testing.camera import FreeRunCameraContract, drain
from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.errors import ConfigError, DeviceError
from rigd.core.events import EventPacket
from rigd.core.frames import Frame
from rigd.core.settings import CameraSettings, EventSensorSettings, TriggerSettings


class CountingCamera(RgbCamera):
    """Free-running 8x8 frames, one per grab; `fail_after` makes the n-th grab raise, `frames`
    (when set) is how many it gives before END."""

    _capabilities = frozenset({Capability.FREE_RUN, Capability.SOFTWARE_SYNC, Capability.EXPOSURE_CONTROL})

    def __init__(
        self, *, queue_len: int = 8, fail_after: int | None = None, frames: int | None = None
    ) -> None:
        super().__init__(CameraSettings(trigger_mode="free_run"), queue_len=queue_len, drop="oldest")
        self._info = DeviceInfo(kind="rgb_camera", spec="counting://0")
        self.fail_after, self.frames = fail_after, frames
        self.grabs = 0
        self.calls: list[str] = []
        self.go = threading.Event()
        self.go.set()
        self.ended = threading.Event()
        """Set when the grab says END: every frame it was to give has been delivered."""

    @property
    def frame_shape(self) -> tuple[int, ...]:
        return (8, 8)

    @property
    def frame_dtype(self) -> np.dtype[np.generic]:
        return np.dtype(np.uint8)

    def _do_configure(self, settings: CameraSettings) -> None:
        self.calls.append("configure")

    def _do_start(self) -> None:
        self.calls.append("start")

    def _do_stop(self) -> None:
        self.calls.append("stop")

    def _do_close(self) -> None:
        self.calls.append("close")

    def _grab(self, timeout_s: float) -> Frame | Signal | None:
        if not self.go.wait(timeout_s):
            return None
        if self.frames is not None and self.grabs >= self.frames:
            self.ended.set()
            return END
        if self.fail_after is not None and self.grabs >= self.fail_after:
            raise OSError("cable pulled")
        self.grabs += 1
        time.sleep(0.002)  # a free-running camera's frame time; no check depends on it
        return Frame(np.zeros((8, 8), np.uint8), self.grabs * 1000, 1000, self.grabs, time.monotonic_ns())


class TestCountingCamera(FreeRunCameraContract):
    """The minimal backend passes the camera contract: the base does the work."""

    @pytest.fixture
    def camera(self) -> Iterator[RgbCamera]:
        cam = CountingCamera(queue_len=1000)
        yield cam
        cam.close()


def test_hooks_run_in_order_and_close_stops_first() -> None:
    cam = CountingCamera()
    cam.configure(CameraSettings(trigger_mode="free_run"))
    cam.start()
    cam.close()
    cam.close()
    assert cam.calls == ["configure", "start", "stop", "close"]


def test_an_acquisition_error_reaches_the_reader_after_the_frames_before_it() -> None:
    cam = CountingCamera(fail_after=3, queue_len=100)
    cam.start()
    frames = [cam.read_frame(1.0) for _ in range(3)]
    assert [f.frame_counter for f in frames if f is not None] == [1, 2, 3]
    with pytest.raises(DeviceError, match="cable pulled") as err:
        cam.read_frame(1.0)
    assert "counting://0" in str(err.value)
    with pytest.raises(DeviceError, match="cable pulled"):  # kept until the next start
        cam.read_frame(0.0)
    cam.stop()  # quiet: the reader was told
    cam.fail_after = None
    cam.start()
    assert cam.read_frame(1.0) is not None
    cam.close()


def test_a_full_queue_gives_up_frames_and_counts_them() -> None:
    cam = CountingCamera(queue_len=4, frames=10)
    cam.start()
    assert cam.ended.wait(30)  # ten frames into a queue of four, nobody reading
    cam.stop()
    kept = drain(cam, 0.05)
    assert [f.frame_counter for f in kept] == [7, 8, 9, 10]  # drop="oldest": the newest stay
    st = cam.stats()
    assert st.device_dropped == 6
    assert st.extra["host_queue_dropped"] == 6
    assert st.delivered == 4


def test_stop_does_not_wait_for_a_grab_that_never_ends_when_not_draining() -> None:
    cam = CountingCamera()
    cam.go.clear()  # every grab idles for its timeout
    cam.start()
    t = time.monotonic()
    cam.stop()
    assert time.monotonic() - t < 0.5
    assert cam.read_frame(0.5) is None
    cam.close()


def test_a_reader_waiting_learns_at_once_that_the_device_ended() -> None:
    cam = CountingCamera(frames=0)
    cam.go.clear()  # the grab idles until the reader waits, then says END
    cam.start()
    threading.Timer(0.2, cam.go.set).start()
    t = time.monotonic()
    assert cam.read_frame(5.0) is None
    assert time.monotonic() - t < 2.0, "the reader waited out its timeout after the end"
    cam.close()


def test_delivery_queue_policies() -> None:
    newest = DeliveryQueue[int](2, "newest")
    assert [newest.put(i) for i in range(4)] == [None, None, 2, 3]
    assert newest.get(0.0, max_items=None) == [0, 1]
    oldest = DeliveryQueue[int](2, "oldest")
    assert [oldest.put(i) for i in range(4)] == [None, None, 0, 1]
    assert oldest.drain() == [2, 3]
    assert (newest.dropped, oldest.dropped) == (2, 2)
    with pytest.raises(ValueError, match=">= 1"):
        DeliveryQueue[int](0)


def test_a_draining_acquisition_finishes_what_the_device_holds() -> None:
    pending = list(range(5))

    def grab(timeout_s: float) -> int | None:
        time.sleep(0.01)  # a device slow to give what it holds, so stop() comes first
        return pending.pop(0) if pending else None

    acq = Acquisition("drain", grab, DeliveryQueue[int](10), drain_on_stop=True)
    acq.start()
    acq.stop()
    assert acq.read(0.0, max_items=None) == [0, 1, 2, 3, 4]
    assert not acq.alive


def test_camera_settings_need_the_capabilities_they_use() -> None:
    cam = CountingCamera()
    need = cam.required_capabilities
    assert need(CameraSettings()) == {Capability.HARDWARE_TRIGGER}
    assert need(CameraSettings(trigger_mode="free_run")) == {Capability.FREE_RUN}
    assert need(CameraSettings(exposure_us=2000, pixel_format="rgb8")) == {
        Capability.HARDWARE_TRIGGER,
        Capability.EXPOSURE_CONTROL,
        Capability.COLOR,
    }
    assert missing_capabilities(cam, need(CameraSettings(pixel_format="rgb8"))) == {
        Capability.HARDWARE_TRIGGER,
        Capability.COLOR,
    }
    with pytest.raises(ConfigError, match=r"counting://0.*color.*hardware_trigger"):
        cam.configure(CameraSettings(pixel_format="rgb8"))
    assert cam.calls == []  # refused before the backend saw it


class EndlessTrigger(Trigger):
    """A trigger without a pulse count: the base refuses counted runs and stops it on close."""

    _capabilities = frozenset({Capability.PULSE_TIMESTAMPS})

    def __init__(self) -> None:
        super().__init__()
        self._info = DeviceInfo(kind="trigger", spec="endless://0")
        self.stops = 0

    def _do_configure(self, settings: TriggerSettings) -> None: ...

    def _do_arm(self) -> None: ...

    def _do_start(self, n_pulses: int | None) -> int:
        return 0

    def _do_stop(self) -> int:
        self.stops += 1
        return 0

    def _is_running(self) -> bool:
        return False

    def _read_pulses(self, timeout_s: float) -> PulseBatch:
        return PulseBatch.empty()

    def _pulse_count(self) -> int:
        return 0

    def _clock_us(self) -> int:
        return 0


def test_trigger_base_refuses_counted_runs_it_cannot_do_and_stops_on_close() -> None:
    trig = EndlessTrigger()
    with pytest.raises(ConfigError, match="pulse_count"):
        trig.start(10)
    assert trig.start() == 0
    trig.close()
    trig.close()
    assert trig.stops == 1
    with pytest.raises(DeviceError, match="endless://0 is closed"):
        trig.clock_us()


class QuietSensor(EventSensor):
    """An event sensor that reads on the caller's thread and never has anything."""

    _capabilities = frozenset({Capability.DEVICE_TIMESTAMPS})

    def __init__(self) -> None:
        super().__init__(EventSensorSettings(enable_trigger_in=False))
        self._info = DeviceInfo(kind="event_sensor", spec="quiet://0")

    @property
    def geometry(self) -> tuple[int, int]:
        return (4, 4)

    def _read(self, timeout_s: float) -> EventPacket | None:
        return None


def test_event_sensor_and_trigger_settings_need_the_capabilities_they_use() -> None:
    sensor, trig = QuietSensor(), EndlessTrigger()
    assert sensor.required_capabilities(EventSensorSettings()) == {Capability.TRIGGER_IN}
    slave = EventSensorSettings(enable_trigger_in=False, sync_mode="slave", sync_master="ev0")
    assert sensor.required_capabilities(slave) == {Capability.CLOCK_SYNC}
    with pytest.raises(ConfigError, match=r"quiet://0.*clock_sync"):
        sensor.configure(slave)
    sensor.configure(EventSensorSettings(enable_trigger_in=False))
    assert trig.required_capabilities(TriggerSettings()) == {Capability.PULSE_TIMESTAMPS}
    assert trig.required_capabilities(TriggerSettings(), n_pulses=5) == {
        Capability.PULSE_TIMESTAMPS,
        Capability.PULSE_COUNT,
    }
    assert missing_capabilities(trig, trig.required_capabilities(TriggerSettings(), n_pulses=5)) == {
        Capability.PULSE_COUNT
    }
