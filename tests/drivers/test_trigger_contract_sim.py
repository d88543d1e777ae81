"""The Trigger contract against the simulated box, opened through the `sim://` entry point,
over both transports: serial (pty) and raw HID (fake hidapi device, 64-byte reports)."""

from __future__ import annotations

from collections.abc import Iterator
from uuid import uuid4

import pytest

from drivers.base import Trigger
from drivers.registry import open_device
from tests.contracts.trigger_contract import TriggerContract


class TestSimSerialTrigger(TriggerContract):
    @pytest.fixture(params=["serial", "hid"])
    def trigger(self, request: pytest.FixtureRequest) -> Iterator[Trigger]:
        trig = open_device("trigger", f"sim://t-{uuid4().hex}/trigger?jitter_us=2&transport={request.param}")
        yield trig
        trig.close()
