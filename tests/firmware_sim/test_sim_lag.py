"""A real-time sim event sensor that falls behind real time skips ahead, counted, instead of
making the backlog (which once kept a loaded capture's stop busy for seconds)."""

from __future__ import annotations

import time
from typing import Any
from uuid import uuid4

import pytest

import firmware_sim.event_sensor as es
from drivers.registry import DeviceSpec
from firmware_sim.world import reset_world
from rigd.core.settings import EventSensorSettings

pytestmark = pytest.mark.slow


def test_a_lagging_generator_skips_ahead_and_counts_it(monkeypatch: pytest.MonkeyPatch) -> None:
    slow_s = 0.1
    real = es.generate_events

    def slow(*args: Any, **kw: Any) -> Any:
        time.sleep(slow_s)  # every slice takes 0.1 s: the generator can never keep up
        return real(*args, **kw)

    monkeypatch.setattr(es, "generate_events", slow)
    monkeypatch.setattr(es, "MAX_LAG_US", 20_000)
    monkeypatch.setattr(es, "_STOP_CATCH_UP_US", 20_000)
    world = f"lag-{uuid4().hex[:8]}"
    sensor = es.open_sim_event_sensor(DeviceSpec.parse(f"sim://{world}/ev0?width=160&height=120"))
    try:
        sensor.configure(EventSensorSettings())
        sensor.start()
        for _ in range(6):  # wait for slices by reading, not by sleeping
            sensor.read_events(1.0)
        sensor.stop()
        extra = sensor.stats().extra
    finally:
        sensor.close()
        reset_world(world)
    # Each slice took 0.1 s of a 20 ms allowance, so every call after the first skipped.
    assert extra["lag_skips"] >= 2
    assert extra["lag_skipped_us"] >= 2 * (slow_s * 1e6 - 20_000 - es.GENERATION_LAG_US - es.SLICE_US)
