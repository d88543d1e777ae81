"""The contract every `EventSensor` backend must pass.

Subclass `EventSensorContract` and provide two fixtures: `sensor` (an opened, stopped
event sensor wired to the rig trigger) and `pulse` (a callable `pulse(n)` that makes the
trigger fire n pulses and returns when they are out).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import pytest

from drivers.base import AcquisitionStats, Capability, EventPacket, EventSensor
from rigd.core.errors import DeviceError
from rigd.core.events import EventArray, TriggerEvents
from rigd.core.settings import EventSensorSettings

Pulse = Callable[[int], object]


def drain(sensor: EventSensor, quiet_s: float = 0.1) -> list[EventPacket]:
    out: list[EventPacket] = []
    while (p := sensor.read_events(quiet_s)) is not None:
        out.append(p)
    return out


class EventSensorContract:
    """Behaviour the daemon relies on, whatever sensor sits behind the interface."""

    def test_info_kind_and_geometry(self, sensor: EventSensor) -> None:
        assert sensor.kind == "event_sensor"
        assert sensor.info.kind == "event_sensor"
        assert sensor.info.spec
        w, h = sensor.geometry
        assert 0 < w <= 65535
        assert 0 < h <= 65535
        caps = sensor.capabilities
        assert isinstance(caps, frozenset)
        assert all(isinstance(c, Capability) for c in caps)
        assert Capability.TRIGGER_IN in caps, "the rig syncs event sensors by trigger-in"

    def test_events_and_triggers_are_well_formed_and_monotonic(
        self, sensor: EventSensor, pulse: Pulse
    ) -> None:
        sensor.configure(EventSensorSettings(trigger_in_channel=0))
        sensor.start()
        packets: list[EventPacket] = []
        pulse(5)
        time.sleep(0.05)
        while (p := sensor.read_events(0.0)) is not None:
            packets.append(p)
        sensor.stop()
        packets += drain(sensor)
        assert packets, "no packets at all"
        w, h = sensor.geometry
        last_ev, last_tr = np.iinfo(np.int64).min, np.iinfo(np.int64).min
        for p in packets:
            assert isinstance(p.events, EventArray)
            assert isinstance(p.triggers, TriggerEvents)
            assert p.host_time_ns > 0
            if len(p.events):
                assert p.events.is_time_sorted()
                assert int(p.events.t[0]) >= last_ev, "event time went back across packets"
                last_ev = int(p.events.t[-1])
                assert int(p.events.x.max()) < w
                assert int(p.events.y.max()) < h
                assert np.isin(p.events.p, (-1, 1)).all()
            if len(p.triggers):
                assert (np.diff(p.triggers.t) >= 0).all()
                assert int(p.triggers.t[0]) >= last_tr, "trigger time went back across packets"
                last_tr = int(p.triggers.t[-1])
        trig = TriggerEvents.concatenate([p.triggers for p in packets])
        assert len(trig.rising(0)) == 5
        assert len(trig) - len(trig.rising()) == 5, "one falling edge per pulse"
        n_events = sum(len(p.events) for p in packets)
        st = sensor.stats()
        assert isinstance(st, AcquisitionStats)
        assert st.delivered == n_events
        assert st.device_dropped == 0

    def test_nothing_latched_while_stopped(self, sensor: EventSensor, pulse: Pulse) -> None:
        pulse(2)
        assert sensor.read_events(0.1) is None

    def test_configure_only_while_stopped(self, sensor: EventSensor) -> None:
        sensor.start()
        try:
            with pytest.raises(DeviceError):
                sensor.configure(EventSensorSettings())
        finally:
            sensor.stop()
        sensor.configure(EventSensorSettings(trigger_in_channel=1))

    def test_stop_and_close_are_idempotent(self, sensor: EventSensor) -> None:
        sensor.stop()
        sensor.start()
        sensor.stop()
        sensor.stop()
        sensor.close()
        sensor.close()
