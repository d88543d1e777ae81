"""The contracts every `EventSensor` backend runs.

`EventSensorLifecycleContract` needs a fixture `sensor`: an opened, stopped event sensor that
produces events once started (a moving scene, a recording). Backends wired to the rig trigger
also run `EventSensorTriggerInContract`, which needs a fixture `pulse`: a callable `pulse(n)`
that makes the trigger fire n pulses and returns when they are out. `EventSensorContract` is
both.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import ClassVar

import numpy as np
import pytest
from pydantic import BaseModel

from drivers.base import AcquisitionStats, Capability, EventSensor
from drivers.testing.lifecycle import Acquiring, AcquiringDeviceContract
from rigd.core.events import EventArray, EventPacket, TriggerEvents
from rigd.core.settings import EventSensorSettings

Pulse = Callable[[int], object]


def drain(sensor: EventSensor, quiet_s: float = 0.1) -> list[EventPacket]:
    """Every packet still to come, until none arrives for `quiet_s`."""
    out: list[EventPacket] = []
    while (p := sensor.read_events(quiet_s)) is not None:
        out.append(p)
    return out


def check_packets(sensor: EventSensor, packets: list[EventPacket]) -> None:
    """Well-formed packets whose event and trigger times never go back."""
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
    hosts = [p.host_time_ns for p in packets]
    assert hosts == sorted(hosts)


class EventSensorLifecycleContract(AcquiringDeviceContract):
    """What the daemon relies on from any event sensor: identity, capabilities that hold, the
    state machine, well-formed monotonic packets. `settings` is how the suite starts it."""

    settings: ClassVar[EventSensorSettings] = EventSensorSettings(enable_trigger_in=False)
    #: How long to read for events after start before giving up.
    events_within_s: ClassVar[float] = 5.0

    @pytest.fixture
    def device(self, sensor: EventSensor) -> EventSensor:
        return sensor

    def _read(self, device: Acquiring, timeout_s: float) -> object | None:
        assert isinstance(device, EventSensor)
        return device.read_events(timeout_s)

    def _asks(self) -> dict[Capability, BaseModel]:
        return {
            Capability.TRIGGER_IN: EventSensorSettings(enable_trigger_in=True),
            Capability.CLOCK_SYNC: EventSensorSettings(enable_trigger_in=False, sync_mode="master"),
        }

    def test_info_kind_geometry_and_capabilities(self, sensor: EventSensor) -> None:
        assert sensor.kind == "event_sensor"
        assert sensor.info.kind == "event_sensor"
        assert sensor.info.spec
        w, h = sensor.geometry
        assert 0 < w <= 65535
        assert 0 < h <= 65535
        caps = sensor.capabilities
        assert isinstance(caps, frozenset)
        assert all(isinstance(c, Capability) for c in caps)

    def test_events_are_well_formed_and_monotonic(self, sensor: EventSensor) -> None:
        self._start(sensor)
        packets: list[EventPacket] = []
        deadline = time.monotonic() + self.events_within_s
        while time.monotonic() < deadline and sum(len(p.events) for p in packets) < 1000:
            if (p := sensor.read_events(0.1)) is not None:
                packets.append(p)
        sensor.stop()
        packets += drain(sensor)
        n_events = sum(len(p.events) for p in packets)
        assert n_events > 0, "no events at all"
        check_packets(sensor, packets)
        st = sensor.stats()
        assert isinstance(st, AcquisitionStats)
        assert st.delivered == n_events
        assert st.device_dropped == 0


class EventSensorTriggerInContract:
    """Trigger edges from the rig's wire, as trigger events in the sensor's clock: needs
    fixtures `sensor` and `pulse`."""

    trigger_settings: ClassVar[EventSensorSettings] = EventSensorSettings(trigger_in_channel=0)

    def test_has_a_trigger_input(self, sensor: EventSensor) -> None:
        assert Capability.TRIGGER_IN in sensor.capabilities, "the rig syncs event sensors by trigger-in"

    def test_every_edge_arrives_once_in_order(self, sensor: EventSensor, pulse: Pulse) -> None:
        sensor.configure(self.trigger_settings)
        sensor.start()
        packets: list[EventPacket] = []
        pulse(5)
        time.sleep(0.05)
        while (p := sensor.read_events(0.0)) is not None:
            packets.append(p)
        sensor.stop()
        packets += drain(sensor)
        assert packets, "no packets at all"
        check_packets(sensor, packets)
        trig = TriggerEvents.concatenate([p.triggers for p in packets])
        channel = self.trigger_settings.trigger_in_channel
        assert len(trig.rising(channel)) == 5
        assert len(trig) - len(trig.rising()) == 5, "one falling edge per pulse"
        st = sensor.stats()
        assert st.delivered == sum(len(p.events) for p in packets)
        assert st.device_dropped == 0

    def test_nothing_latched_while_stopped(self, sensor: EventSensor, pulse: Pulse) -> None:
        pulse(2)
        assert sensor.read_events(0.1) is None
        sensor.configure(self.trigger_settings)
        sensor.start()
        sensor.stop()
        triggers = [p.triggers for p in drain(sensor)]
        assert sum(len(t) for t in triggers) == 0, "edges from before start were latched"


class EventSensorContract(EventSensorLifecycleContract, EventSensorTriggerInContract):
    """Both contracts: an event sensor wired to the rig trigger."""
