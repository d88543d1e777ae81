"""The camera and event-sensor contracts against the simulators, opened through `sim://` specs."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from uuid import uuid4

import pytest

from drivers.base import EventSensor, RgbCamera
from drivers.registry import DeviceSpec
from firmware_sim.event_sensor import open_sim_event_sensor
from firmware_sim.rgb_camera import open_sim_camera
from firmware_sim.world import get_world, reset_world
from tests.contracts.camera_contract import RgbCameraContract
from tests.contracts.event_sensor_contract import EventSensorContract
from tests.firmware_sim.test_sim_rgb_camera import fire_pulses


@pytest.fixture
def world_name() -> Iterator[str]:
    name = f"t-{uuid4().hex}"
    yield name
    reset_world(name)


@pytest.fixture
def pulse(world_name: str) -> Callable[[int], object]:
    world = get_world(world_name)
    return lambda n: fire_pulses(world, n, rate_hz=100.0)


class TestSimRgbCamera(RgbCameraContract):
    @pytest.fixture
    def camera(self, world_name: str) -> Iterator[RgbCamera]:
        cam = open_sim_camera(DeviceSpec.parse(f"sim://{world_name}/cam1?drift_ppm=-60&width=320&height=180"))
        yield cam
        cam.close()


class TestSimRgbCameraMono(RgbCameraContract):
    @pytest.fixture
    def camera(self, world_name: str) -> Iterator[RgbCamera]:
        cam = open_sim_camera(DeviceSpec.parse(f"sim://{world_name}/cam2?format=mono8&width=160&height=90"))
        yield cam
        cam.close()


class TestSimEventSensor(EventSensorContract):
    @pytest.fixture
    def sensor(self, world_name: str) -> Iterator[EventSensor]:
        ev = open_sim_event_sensor(
            DeviceSpec.parse(f"sim://{world_name}/ev1?drift_ppm=100&width=320&height=180")
        )
        yield ev
        ev.close()
