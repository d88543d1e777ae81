"""The state machine every camera and event sensor shares, as one contract their kind's
contracts build on (`drivers.testing.camera`, `drivers.testing.event_sensor`)."""

from __future__ import annotations

import time
from typing import Any, ClassVar

import pytest
from pydantic import BaseModel

from drivers.base import AcquiringDevice, Capability
from rigd.core.errors import ConfigError, DeviceError

Acquiring = AcquiringDevice[Any, Any]


class AcquiringDeviceContract:
    """Needs a fixture `device`: the opened, stopped device. The kind's contract says how to
    start it (`settings`), how to read from it and which settings need which capability."""

    settings: ClassVar[BaseModel]

    def _start(self, device: Acquiring) -> None:
        device.configure(self.settings)
        device.start()

    def _read(self, device: Acquiring, timeout_s: float) -> object | None:
        raise NotImplementedError

    def _asks(self) -> dict[Capability, BaseModel]:
        """Settings that need a capability, one per capability the kind knows."""
        raise NotImplementedError

    def test_its_settings_need_only_what_it_has(self, device: Acquiring) -> None:
        assert device.required_capabilities(self.settings) <= device.capabilities

    def test_configure_refuses_what_it_lacks(self, device: Acquiring) -> None:
        for cap, settings in self._asks().items():
            assert cap in device.required_capabilities(settings)
            if cap not in device.capabilities:
                with pytest.raises(ConfigError, match=str(cap)):
                    device.configure(settings)

    def test_nothing_to_read_before_start(self, device: Acquiring) -> None:
        t = time.monotonic()
        assert self._read(device, 0.1) is None
        assert time.monotonic() - t < 1.0

    def test_configure_only_while_stopped(self, device: Acquiring) -> None:
        self._start(device)
        assert device.acquiring
        try:
            with pytest.raises(DeviceError, match="stop it first"):
                device.configure(self.settings)
            with pytest.raises(DeviceError, match="already started"):
                device.start()
        finally:
            device.stop()
        assert not device.acquiring
        device.configure(self.settings)

    def test_stop_and_close_are_idempotent(self, device: Acquiring) -> None:
        device.stop()
        self._start(device)
        device.stop()
        device.stop()
        self._start(device)
        device.close()  # stops first
        assert not device.acquiring
        device.close()

    def test_a_closed_device_says_so_naming_itself(self, device: Acquiring) -> None:
        device.close()
        assert device.closed
        for call in (device.start, lambda: self._read(device, 0.0), lambda: device.configure(self.settings)):
            with pytest.raises(DeviceError, match="closed") as err:
                call()
            assert device.label in str(err.value)
