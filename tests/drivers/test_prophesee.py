"""`prophesee://` backend: the clear error without OpenEB, and the real code path against a
stand-in HAL module: it streams a real recording's raw EVT3 buffers, and, for the event-sensor
contracts, a synthetic scene whose trigger-in latches the test's pulses."""

from __future__ import annotations

import sys
import threading
import time
import types
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.base import Capability, EventSensor
from drivers.registry import open_device
from drivers.testing.event_sensor import EventSensorContract, drain
from rigd.core.errors import BackendUnavailableError, ConfigError
from rigd.core.events import EventArray, TriggerEvents
from rigd.core.settings import EventSensorSettings
from rigd.evt import Evt3Encoder, parse_raw_header, read_raw

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "events"


def test_missing_openeb_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "metavision_hal", None)  # import fails as if not installed
    with pytest.raises(BackendUnavailableError, match=r"metavision_hal.*not installed"):
        open_device("event_sensor", "prophesee://00050423")


class _Facility:
    def __init__(self, log: list[tuple[str, Any]], name: str) -> None:
        self._log, self._name = log, name

    def __getattr__(self, method: str) -> Any:
        def call(*args: Any) -> bool:
            self._log.append((f"{self._name}.{method}", args))
            return True

        return call


class _Stream:
    """I_EventsStream: raw buffers while started. `pulse(n)` latches n trigger pulses on
    channel 0 (1 ms apart, 200 us wide) after the events already streamed."""

    def __init__(self, payload: bytes, chunk: int, *, last_t: int = 0) -> None:
        self._chunks = [payload[i : i + chunk] for i in range(0, len(payload), chunk)]
        self._lock = threading.Lock()
        self._started = False
        self._encoder = Evt3Encoder()
        self._t = last_t

    def start(self) -> None:
        self._started = True

    def stop(self) -> None:
        self._started = False

    def poll_buffer(self) -> int:
        with self._lock:
            return 1 if self._started and self._chunks else -1

    def get_latest_raw_data(self) -> np.ndarray:
        with self._lock:
            return np.frombuffer(self._chunks.pop(0), np.uint8)

    def pulse(self, n: int) -> None:
        if not self._started:
            return  # the camera is not streaming: nothing is latched
        t = self._t + 1000 + np.repeat(np.arange(n, dtype=np.int64) * 1000, 2)
        t[1::2] += 200
        p = np.tile(np.array([1, 0], np.uint8), n)
        with self._lock:
            self._chunks.append(
                self._encoder.encode(EventArray.empty(), TriggerEvents(t, p, np.zeros_like(p)))
            )
            self._t = int(t[-1])


def _fake_hal(
    payload: bytes, calls: list[tuple[str, Any]], *, has_roi: bool = True, stream: _Stream | None = None
) -> types.ModuleType:
    class Device:
        def get_i_geometry(self) -> Any:
            return types.SimpleNamespace(get_width=lambda: 1280, get_height=lambda: 720)

        def get_i_hw_identification(self) -> Any:
            return types.SimpleNamespace(
                get_serial=lambda: "00050423",
                get_current_data_encoding_format=lambda: "EVT3",
                get_sensor_info=lambda: "IMX636",
            )

        def get_i_events_stream(self) -> _Stream:
            return stream if stream is not None else _Stream(payload, 4093)

        def get_i_trigger_in(self) -> Any:
            return _Facility(calls, "trigger_in")

        def get_i_camera_synchronization(self) -> Any:
            return _Facility(calls, "sync")

        def get_i_ll_biases(self) -> Any:
            return _Facility(calls, "biases")

        def get_i_roi(self) -> Any:
            return _Facility(calls, "roi") if has_roi else None

        def get_i_erc_module(self) -> Any:
            return _Facility(calls, "erc")

    hal = types.ModuleType("metavision_hal")
    hal.DeviceDiscovery = types.SimpleNamespace(open=lambda serial: Device())  # type: ignore[attr-defined]
    hal.I_ROI = types.SimpleNamespace(Window=lambda *a: a)  # type: ignore[attr-defined]
    return hal


@pytest.mark.skipif(not DATA.is_dir(), reason=f"shared test data not found at {DATA}")
def test_hal_buffers_go_through_rigd_decoder(monkeypatch: pytest.MonkeyPatch) -> None:
    path = DATA / "evt3_gen41_sample.raw"
    with path.open("rb") as f:
        parse_raw_header(f)
        payload = f.read()
    calls: list[tuple[str, Any]] = []
    monkeypatch.setitem(sys.modules, "metavision_hal", _fake_hal(payload, calls))
    sensor = open_device("event_sensor", "prophesee://00050423")
    assert sensor.info.serial == "00050423"
    assert sensor.geometry == (1280, 720)
    sensor.configure(
        EventSensorSettings(
            trigger_in_channel=0,
            sync_mode="master",
            biases={"bias_diff_on": 12},
            roi=(0, 0, 640, 360),
            erc_rate_ev_s=20e6,
        )
    )
    names = [c[0] for c in calls]
    for expected in (
        "trigger_in.enable",
        "sync.set_mode_master",
        "biases.set",
        "roi.set_window",
        "erc.set_cd_event_rate",
    ):
        assert expected in names
    sensor.start()
    packets = []
    while (p := sensor.read_events(0.3)) is not None:
        packets.append(p)
    sensor.close()
    ev = EventArray.concatenate([p.events for p in packets])
    _, whole = read_raw(path)
    np.testing.assert_array_equal(ev.t, whole.events.t)
    np.testing.assert_array_equal(ev.x, whole.events.x)


def test_missing_facility_is_named(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "metavision_hal", _fake_hal(b"", [], has_roi=False))
    sensor = open_device("event_sensor", "prophesee://00050423")
    with pytest.raises(ConfigError, match="no ROI facility"):
        sensor.configure(EventSensorSettings(roi=(0, 0, 10, 10)))


def _synthetic_stream() -> _Stream:
    """20 000 events of a bar sweeping the sensor, 50 ms; trigger pulses follow on demand."""
    n = 20_000
    t = np.arange(n, dtype=np.int64) * 2 + 100
    x = (t // 10) % 1280
    ev = EventArray.from_arrays(x, (t // 7) % 720, np.where(t % 4 == 0, 1, -1), t)
    stream = _Stream(b"", 4093, last_t=int(t[-1]))
    stream._chunks = [
        stream._encoder.encode(ev[i : i + 2000], TriggerEvents.empty()) for i in range(0, n, 2000)
    ]
    return stream


def test_a_full_host_queue_loses_whole_buffers_and_counts_them(monkeypatch: pytest.MonkeyPatch) -> None:
    stream = _synthetic_stream()  # ten buffers of 2000 events
    sizes = [len(c) for c in stream._chunks]
    monkeypatch.setitem(sys.modules, "metavision_hal", _fake_hal(b"", [], stream=stream))
    sensor = open_device("event_sensor", "prophesee://00050423?buffers=2")
    sensor.start()
    deadline = time.monotonic() + 10
    while stream._chunks and time.monotonic() < deadline:  # nobody reads: two buffers fit
        time.sleep(0.01)
    sensor.stop()
    packets = drain(sensor)
    st = sensor.stats()
    sensor.close()
    assert st.device_dropped == st.extra["buffers_lost"] == 8
    assert st.extra["bytes_lost"] == sum(sizes[2:])
    assert st.delivered == sum(len(p.events) for p in packets) == 4000
    assert st.extra["bytes_decoded"] == sum(sizes[:2])


class TestPropheseeStandIn(EventSensorContract):
    """The event-sensor contracts through the HAL code path, the stand-in in place of OpenEB."""

    @pytest.fixture
    def stream(self) -> _Stream:
        return _synthetic_stream()

    @pytest.fixture
    def sensor(self, stream: _Stream, monkeypatch: pytest.MonkeyPatch) -> Iterator[EventSensor]:
        monkeypatch.setitem(sys.modules, "metavision_hal", _fake_hal(b"", [], stream=stream))
        sensor = open_device("event_sensor", "prophesee://00050423")
        assert {Capability.TRIGGER_IN, Capability.CLOCK_SYNC} <= sensor.capabilities
        yield sensor
        sensor.close()

    @pytest.fixture
    def pulse(self, stream: _Stream) -> Callable[[int], None]:
        return stream.pulse
