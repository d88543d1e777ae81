"""The camera and event-sensor contracts against the simulators, opened through `sim://` specs."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from uuid import uuid4

import pytest

from drivers.base import EventSensor, RgbCamera
from drivers.registry import DeviceSpec
from drivers.testing.camera import FreeRunCameraContract, HardwareTriggerCameraContract
from drivers.testing.event_sensor import EventSensorContract
from firmware_sim.event_sensor import open_sim_event_sensor
from firmware_sim.rgb_camera import open_sim_camera
from firmware_sim.testing.wire import fire_pulses
from firmware_sim.world import get_world, reset_world


@pytest.fixture
def world_name() -> Iterator[str]:
    name = f"t-{uuid4().hex}"
    yield name
    reset_world(name)


@pytest.fixture
def pulse(world_name: str) -> Callable[[int], object]:
    world = get_world(world_name)
    return lambda n: fire_pulses(world, n, rate_hz=100.0)


def _camera(world_name: str, query: str) -> Iterator[RgbCamera]:
    cam = open_sim_camera(DeviceSpec.parse(f"sim://{world_name}/cam1?{query}"))
    yield cam
    cam.close()


class TestSimRgbCamera(HardwareTriggerCameraContract):
    @pytest.fixture
    def camera(self, world_name: str) -> Iterator[RgbCamera]:
        yield from _camera(world_name, "drift_ppm=-60&width=320&height=180")


class TestSimRgbCameraMono(HardwareTriggerCameraContract):
    @pytest.fixture
    def camera(self, world_name: str) -> Iterator[RgbCamera]:
        yield from _camera(world_name, "format=mono8&width=160&height=90")


class TestSimRgbCameraFreeRun(FreeRunCameraContract):
    @pytest.fixture
    def camera(self, world_name: str) -> Iterator[RgbCamera]:
        yield from _camera(world_name, "drift_ppm=40&width=160&height=90")


class TestSimEventSensor(EventSensorContract):
    @pytest.fixture
    def sensor(self, world_name: str) -> Iterator[EventSensor]:
        ev = open_sim_event_sensor(
            DeviceSpec.parse(f"sim://{world_name}/ev1?drift_ppm=100&width=320&height=180")
        )
        yield ev
        ev.close()
