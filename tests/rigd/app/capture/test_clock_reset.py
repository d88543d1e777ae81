"""Tying a restarted device clock back onto the old one (synthetic pulses, exact truth)."""

from __future__ import annotations

import numpy as np

from rigd.app.capture.clock_reset import MAX_HOLD_S, MIN_OBSERVATIONS, ClockReset, Offset, estimate_offset
from rigd.app.capture.kinds import CameraReading, EventReading
from rigd.core.events import EventArray, EventPacket, TriggerEvents
from rigd.core.frames import Frame
from rigd.core.settings import CameraSettings, EventSensorSettings
from rigd.sync import PulseLog

PERIOD = 33_333.0
#: The kinds' reading parts: how re-tying counts, observes and shifts their items.
CAMERA = CameraReading("cam1", CameraSettings())
SENSOR = EventReading("ev1", EventSensorSettings(trigger_in_channel=0))
DRIFT = 1 + 80e-6  # device us per rig us


def _pulses(n: int) -> PulseLog:
    t = 5_000_000 + (np.arange(n) * PERIOD).astype(np.int64)
    return PulseLog(np.arange(n, dtype=np.int64), t, (t + 1_000) * 1_000, n)


def _frame(t: int, host_ns: int) -> Frame:
    return Frame(np.zeros((2, 2), np.uint8), t, 100, 0, host_ns)


def test_offset_matches_truth_across_a_drifting_gap() -> None:
    pulses = _pulses(120)
    rig = pulses.t_us.astype(np.float64)
    old = np.floor(123_456 + (rig - rig[0]) * DRIFT).astype(np.int64)  # old clock
    restart = rig[70]  # power-up: the new counter is 0 at this rig time
    new = np.floor((rig - restart) * DRIFT + 17).astype(np.int64)
    latency = 8_000 * 1_000  # frames arrive 8 ms after their pulse
    pre = np.arange(0, 40)  # observed before the unplug
    post = np.arange(75, 75 + MIN_OBSERVATIONS)  # after the replug
    reset = ClockReset("cam1", CAMERA, int(old[pre[-1]]))
    for k in post:
        reset.hold(_frame(int(new[k]), int(pulses.host_time_ns[k]) + latency))
    host_pre = pulses.host_time_ns[pre] + latency
    got = estimate_offset(reset, old[pre], host_pre, pulses, PERIOD)
    assert got is not None
    truth = old[post] - new[post]
    assert abs(got.us - float(np.median(truth))) <= 2, (got, truth)
    assert got.n == MIN_OBSERVATIONS
    # The held frames come back on the old clock, in order, and the hold is empty.
    reset.offset = got
    released = reset.release()
    t = [f.t_exposure_start_us for f in released]
    assert np.abs(np.asarray(t) - old[post]).max() <= 2
    assert not reset.held


def test_too_few_observations_or_no_history_wait() -> None:
    pulses = _pulses(60)
    reset = ClockReset("cam1", CAMERA, 1_000)
    for k in range(MIN_OBSERVATIONS - 1):
        reset.hold(_frame(k * 33_333, int(pulses.host_time_ns[k])))
    t = pulses.t_us[:20]
    assert estimate_offset(reset, t, pulses.host_time_ns[:20], pulses, PERIOD) is None
    reset.hold(_frame(5 * 33_333, int(pulses.host_time_ns[5])))
    assert estimate_offset(reset, t[:2], pulses.host_time_ns[:2], pulses, PERIOD) is None


def test_event_packets_shift_events_and_triggers_and_count_what_is_held() -> None:
    reset = ClockReset("ev1", SENSOR, 1_000)
    ev = EventArray.from_arrays([1, 2, 3], [1, 1, 1], [1, 0, 1], [10, 20, 30])
    trig = TriggerEvents(np.array([15, 16], np.int64), np.array([1, 0], np.uint8), np.zeros(2, np.uint8))
    reset.hold(EventPacket(ev, trig, 99))
    assert reset.post_t == [15]  # the rising edge only
    assert reset.held_count() == 3
    reset.offset = Offset(1_000, 5, 1.0)
    (packet,) = reset.release()
    assert packet.events.t.tolist() == [1_010, 1_020, 1_030]
    assert packet.triggers.t.tolist() == [1_015, 1_016]
    assert packet.host_time_ns == 99


def test_hold_is_bounded_in_time_for_sensors_without_trigger_edges() -> None:
    """A sensor whose trigger input is not wired never ties: the pipeline writes it off once its
    held data spans MAX_HOLD_S (measured on host time)."""
    reset = ClockReset("ev1", SENSOR, 1_000)
    ev = EventArray.from_arrays([1], [1], [1], [10])
    none = TriggerEvents.empty()
    for host_s in (0.0, 2.5, 6.0):
        reset.hold(EventPacket(ev, none, int(host_s * 1e9)))
    assert reset.post_t == []
    assert reset.held_for_s() == 6.0
    assert reset.held_for_s() > MAX_HOLD_S
