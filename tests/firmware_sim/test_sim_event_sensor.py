"""The simulated event sensor: events from real motion only, exact trigger stamps, honest losses."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from uuid import uuid4

import numpy as np
import pytest

from drivers.registry import DeviceSpec
from firmware_sim.clock import VirtualHostClock
from firmware_sim.event_kernels import EventBuffer, generate_events, generate_events_kernel
from firmware_sim.event_sensor import GENERATION_LAG_US, SLICE_US, SimEventSensor, open_sim_event_sensor
from firmware_sim.scene import Scene, lin_log
from firmware_sim.testing.wire import fire_pulses
from firmware_sim.world import DeviceClock, SimWorld, get_world, reset_world
from rigd.core.errors import ConfigError
from rigd.core.events import EventArray, EventPacket, TriggerEvents
from rigd.core.settings import EventSensorSettings

C = 0.3


def run_kernel(l0: float, l1: float, ref: float, cap: int = 64) -> tuple[EventArray, float]:
    lp = np.array([[l0]], np.float32)
    ln = np.array([[l1]], np.float32)
    r = np.array([[ref]], np.float32)
    buf = EventBuffer(cap)
    n, nxt = generate_events_kernel(lp, ln, r, C, 1000.0, 2000.0, 7, 9, (0.0, 1.0), 0, buf.columns, 0)
    assert nxt == 1
    return EventArray(buf.x[:n], buf.y[:n], buf.p[:n], buf.t[:n]), float(r[0, 0])


@pytest.mark.slow
@pytest.mark.parametrize("k", [0, 1, 2, 5])
@pytest.mark.parametrize("sign", [1, -1])
def test_kernel_ramp_of_k_thresholds_gives_k_interpolated_events(k: int, sign: int) -> None:
    l0 = 4.0
    ev, ref = run_kernel(l0, l0 + sign * (k * C + 0.05), l0)
    assert len(ev) == k
    assert (ev.p == sign).all()
    assert (ev.x == 7).all()
    assert (ev.y == 9).all()
    # Crossing m at fraction m*C / (k*C + 0.05) of the 1000 us sub-step.
    expected = [int(np.floor(1000.0 + 1000.0 * m * C / (k * C + 0.05))) for m in range(1, k + 1)]
    assert ev.t.tolist() == pytest.approx(expected, abs=1)
    assert len(set(ev.t.tolist())) == k  # never all on the sub-step time
    assert ref == pytest.approx(l0 + sign * k * C, abs=1e-5)


def test_kernel_below_threshold_keeps_reference_and_resumes_when_full() -> None:
    ev, ref = run_kernel(4.0, 4.0 + 0.9 * C, 4.0)
    assert len(ev) == 0
    assert ref == pytest.approx(4.0)
    # Two pixels of 3 events each into room for 4: stops before pixel 1, resumes after growing.
    lp = np.full((1, 2), 4.0, np.float32)
    ln = np.full((1, 2), 4.0 + 3.5 * C, np.float32)
    r = lp.copy()
    buf = EventBuffer(4)
    n, nxt = generate_events_kernel(lp, ln, r, C, 0.0, 100.0, 0, 0, (0.0, 1.0), 0, buf.columns, 0)
    assert (n, nxt) == (3, 1)
    buf.n = n
    buf.grow()
    n, nxt = generate_events_kernel(lp, ln, r, C, 0.0, 100.0, 0, 0, (0.0, 1.0), nxt, buf.columns, n)
    assert (n, nxt) == (6, 2)
    assert buf.x[:6].tolist() == [0, 0, 0, 1, 1, 1]


def test_generated_events_integrate_to_the_rendered_log_change() -> None:
    scene = Scene(seed=5)
    view = scene.view("ev0", 320, 180)
    t0, t1 = 2.0e6, 2.1e6
    last = lin_log(scene.render_intensity(view, t0))
    ref = last.copy()
    ref0 = ref.copy()
    clock = DeviceClock(100.0, 50.0)
    buf = EventBuffer(16)  # forces growth
    t = t0
    while t < t1:
        generate_events(scene, view, last, ref, C, t, t + 5000.0, clock, buf)
        t += 5000.0
    ev = buf.to_array()
    assert len(ev) > 1000
    assert ev.is_time_sorted()
    assert ev.t.min() >= clock.stamp(t0)
    assert ev.t.max() <= clock.stamp(t1)
    net = np.zeros((180, 320))
    np.add.at(net, (ev.y.astype(int), ev.x.astype(int)), ev.p.astype(float))
    np.testing.assert_allclose(ref - ref0, net * C, atol=1e-4)
    # The reference tracks the true image within one threshold.
    truth = lin_log(scene.render_intensity(view, t1))
    assert np.abs(truth - ref).max() < C + 0.02
    # The kernel samples sprites itself; cv2 quantises sub-pixel positions to 1/32 px.
    err = np.abs(truth - last)
    assert err.max() < 0.1
    assert err.mean() < 1e-3
    assert (ev.p == 1).any()
    assert (ev.p == -1).any()


@pytest.fixture
def world_name() -> Iterator[str]:
    name = f"t-{uuid4().hex}"
    yield name
    reset_world(name)


def open_ev(world: str, extra: str = "") -> SimEventSensor:
    return open_sim_event_sensor(
        DeviceSpec.parse(f"sim://{world}/ev0?offset_us=412775&drift_ppm=-95&width=320&height=180{extra}")
    )


def drain(sensor: SimEventSensor) -> list[EventPacket]:
    out = []
    while (p := sensor.read_events(0.05)) is not None:
        out.append(p)
    return out


#: Spec tail of a sensor on its world's virtual clock: the same events whatever the machine's load.
VIRTUAL = "&clock=virtual"


def run_virtual(
    sensor: SimEventSensor, world: SimWorld, seconds: float, *, read: bool = True
) -> list[EventPacket]:
    """Let a started sensor run `seconds` of its world's virtual time from now, reading what it
    makes (or not, `read=False`: its FIFO fills), then stop it at that very instant and drain
    it. Time is held at the end while the sensor stops, so its last slice ends there."""
    hold = world.hold()
    until = world.now_us() + seconds * 1e6
    reached = threading.Event()

    def sleeper() -> None:
        assert hold.sleep_until(until)
        reached.set()

    threading.Thread(target=sleeper, name="test-run-virtual", daemon=True).start()
    world.clock.start()
    packets: list[EventPacket] = []
    while not reached.wait(0 if read else 0.05):
        if read and (p := sensor.read_events(0.05)) is not None:
            packets.append(p)
    assert world.now_us() == until
    if read:
        packets += drain(sensor)  # so the last slice finds room at once
    sensor.stop()
    hold.release()
    return packets + drain(sensor)


def test_moving_scene_gives_sorted_in_range_events(world_name: str) -> None:
    with open_ev(world_name, VIRTUAL) as sensor:
        assert sensor.geometry == (320, 180)
        sensor.start()
        packets = run_virtual(sensor, get_world(world_name), 0.5)
    ev = EventArray.concatenate([p.events for p in packets])
    assert len(ev) > 1000
    assert ev.t.dtype == np.int64
    assert ev.is_time_sorted()
    assert int(ev.x.max()) < 320
    assert int(ev.y.max()) < 180
    assert set(np.unique(ev.p).tolist()) == {-1, 1}
    st = sensor.stats()
    assert st.delivered == len(ev) == st.extra["events_generated"]
    assert st.device_dropped == 0


def test_packets_on_virtual_time_carry_the_world_host_time_of_their_slice(world_name: str) -> None:
    """On the virtual clock a sensor hands a slice over at the virtual instant it is made
    (`GENERATION_LAG_US` past its end, on the slice grid), and stamps it with the world's host
    clock there: epoch + that instant, nothing of the machine's own clock."""
    world = get_world(world_name, clock="virtual")
    host = world.host_clock
    assert isinstance(host, VirtualHostClock)
    with open_ev(world_name, VIRTUAL) as sensor:
        assert sensor.host_clock is host
        sensor.start()
        packets = run_virtual(sensor, world, 0.3)
    at_ns = np.array([p.host_time_ns for p in packets], np.int64) - host.epoch_ns
    assert len(at_ns) > 3
    assert (np.diff(at_ns) >= 0).all()
    assert at_ns[0] >= (SLICE_US + GENERATION_LAG_US) * 1000
    assert at_ns[-1] <= 300_000_000
    assert (at_ns % (SLICE_US * 1000) == 0).all()  # GENERATION_LAG_US is whole slices


def test_static_scene_gives_no_events(world_name: str) -> None:
    world = get_world(world_name, clock="virtual")
    world.resource("scene", lambda: Scene(seed=0, speed=0.0))
    with open_ev(world_name, VIRTUAL) as sensor:
        sensor.start()
        packets = run_virtual(sensor, world, 0.2)  # 0.2 s of sim time, however long it took
        assert sum(len(p.events) + len(p.triggers) for p in packets) == 0
        assert sensor.stats().extra["events_generated"] == 0


def test_trigger_in_edges_are_stamped_in_the_sensor_clock(world_name: str) -> None:
    world = get_world(world_name)
    world.resource("scene", lambda: Scene(seed=0, speed=0.0))
    with open_ev(world_name) as sensor:
        sensor.configure(EventSensorSettings(trigger_in_channel=3))
        fire_pulses(world, 2)  # not started: not latched
        sensor.start()
        rising = fire_pulses(world, 6, rate_hz=100)
        sensor.stop()
        fire_pulses(world, 2)
        packets = drain(sensor)
    trig = TriggerEvents.concatenate([p.triggers for p in packets])
    expected = sorted([(t, 1) for t in rising] + [(t + 500.0, 0) for t in rising])
    assert trig.t.tolist() == [sensor.clock.stamp(t) for t, _ in expected]
    assert trig.p.tolist() == [p for _, p in expected]
    assert (trig.channel == 3).all()
    assert get_world(world_name).truth.clocks["ev0"] is sensor.clock


def test_trigger_in_can_be_disabled(world_name: str) -> None:
    world = get_world(world_name)
    world.resource("scene", lambda: Scene(seed=0, speed=0.0))
    with open_ev(world_name) as sensor:
        sensor.configure(EventSensorSettings(enable_trigger_in=False))
        sensor.start()
        fire_pulses(world, 3)
        sensor.stop()
        # Nothing latched, nothing generated (a packet may still say how far time got).
        assert sum(len(p.events) + len(p.triggers) for p in drain(sensor)) == 0


def test_packet_buffer_overflow_is_counted(world_name: str) -> None:
    """Nobody reads: a FIFO of two packets overflows. Real time on purpose: on virtual time a
    sensor waits for room instead of dropping, so only a real-time sensor loses packets."""
    world = get_world(world_name)
    with open_ev(world_name, "&buffer_packets=2") as sensor:
        sensor.start()
        fire_pulses(world, 5, rate_hz=50)
        deadline = time.monotonic() + 30.0  # wait for the state, not a fixed time
        while sensor.stats().extra["packets_dropped"] == 0:
            assert time.monotonic() < deadline, "the FIFO never overflowed"
            time.sleep(0.01)
        sensor.stop()
        packets = drain(sensor)
    st = sensor.stats()
    delivered = sum(len(p.events) for p in packets)
    assert st.extra["packets_dropped"] > 0
    assert st.device_dropped == st.extra["events_generated"] - delivered > 0
    assert st.extra["triggers_dropped"] == 10 - sum(len(p.triggers) for p in packets)


def test_bad_specs_name_the_parameter(world_name: str) -> None:
    for bad, word in (
        ("threshold=0", "threshold"),
        ("threshold=x", "threshold"),
        ("buffer_packets=0", "buffer_packets"),
        ("format=rgb8", "format"),
        ("height=0", "height"),
    ):
        with pytest.raises(ConfigError, match=word):
            open_sim_event_sensor(DeviceSpec.parse(f"sim://{world_name}/ev1?{bad}"))


def _events_for(world: str, extra: str, seconds: float = 0.4) -> EventArray:
    """`seconds` of the world's virtual time, from where the last sensor left it."""
    with open_ev(world, extra + VIRTUAL) as sensor:
        sensor.start()
        return EventArray.concatenate([p.events for p in run_virtual(sensor, get_world(world), seconds)])


@pytest.mark.slow
def test_full_pixel_model_runs_in_the_rig_sensor(world_name: str) -> None:
    """`pixel_model=full` puts the seeded pixel model of firmware_sim.event_model behind the
    rig's sensor: with noise off it sees the same motion as the ideal kernel, and its noise
    terms add events where nothing moves."""
    ideal = _events_for(world_name, "")
    full = _events_for(world_name, "&pixel_model=full")
    assert len(full) > 0
    assert 0.3 < len(full) / len(ideal) < 3.0  # same scene, same threshold (different windows)
    assert full.is_time_sorted()
    noisy = _events_for(world_name, "&pixel_model=full&shot_hz=20&sigma=0.03")
    assert noisy.is_time_sorted()
    # Shot noise fires all over the sensor, not only where sprites move.
    assert len(np.unique(noisy.y)) > len(np.unique(full.y))


def test_model_parameters_need_the_full_model(world_name: str) -> None:
    with pytest.raises(ConfigError, match="need pixel_model=full"):
        open_ev(world_name, "&sigma=0.03")
    with pytest.raises(ConfigError, match="pixel_model='fancy'"):
        open_ev(world_name, "&pixel_model=fancy")
