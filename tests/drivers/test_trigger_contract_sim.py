"""The Trigger contract against the simulated box: through the `sim://` entry point over both
transports (serial on a pty, raw HID through a fake hidapi device), and through the plain
`serial://` and `hid://` specs a real box is opened with."""

from __future__ import annotations

from collections.abc import Iterator
from uuid import uuid4

import pytest

from drivers import trigger_link
from drivers.base import Trigger
from drivers.registry import open_device
from drivers.testing.trigger import TriggerContract
from firmware_sim.hid_box import SIM_HID_PID, SIM_HID_VID, FakeHidApi, attach
from firmware_sim.trigger_box import SimTriggerBox
from firmware_sim.world import get_world, reset_world


@pytest.fixture
def world_name() -> Iterator[str]:
    name = f"t-{uuid4().hex}"
    yield name
    reset_world(name)


class TestSimTrigger(TriggerContract):
    @pytest.fixture(params=["serial", "hid"])
    def trigger(self, request: pytest.FixtureRequest, world_name: str) -> Iterator[Trigger]:
        trig = open_device("trigger", f"sim://{world_name}/trigger?jitter_us=2&transport={request.param}")
        yield trig
        trig.close()


class TestSerialSpecTrigger(TriggerContract):
    """`serial:///dev/pts/N`: the driver on the pty as on a USB-serial box."""

    @pytest.fixture
    def trigger(self, world_name: str) -> Iterator[Trigger]:
        box = SimTriggerBox(get_world(world_name), boot_ms=0, jitter_us=2)
        try:
            trig = open_device("trigger", f"serial://{box.port_path}?reply_timeout_s=2")
            yield trig
            trig.close()
        finally:
            box.close()


class TestHidSpecTrigger(TriggerContract):
    """`hid://VID:PID/SERIAL` with the fake hidapi module in place of `hid`."""

    @pytest.fixture
    def trigger(self, world_name: str, monkeypatch: pytest.MonkeyPatch) -> Iterator[Trigger]:
        monkeypatch.setattr(trigger_link, "_import_hid", lambda: FakeHidApi)
        box = SimTriggerBox(get_world(world_name), boot_ms=0, seed=7, link="socket")
        try:
            attach(box)
            trig = open_device(
                "trigger", f"hid://{SIM_HID_VID:04x}:{SIM_HID_PID:04x}/SIM0007?reply_timeout_s=2"
            )
            yield trig
            trig.close()
        finally:
            box.close()
