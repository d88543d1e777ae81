"""The protocol contract (drivers.testing.trigger_protocol) against the AVR firmware: the
image a lab flashes, run under simavr in real time, spoken to with raw pyserial on its pty.
The same suite runs against the Python model in tests/firmware_sim/test_trigger_box.py."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from drivers.testing.trigger_protocol import RawPort, TriggerProtocolContract
from firmware_sim.testing.avr_box import FirmwareProcess


class TestAvrProtocol(TriggerProtocolContract):
    min_width_us = 16

    @pytest.fixture(params=["atmega328p", "atmega2560"])
    def port(self, request: pytest.FixtureRequest, serve: type[FirmwareProcess]) -> Iterator[RawPort]:
        box = serve(request.param)
        port = RawPort(box.port, baudrate=1_000_000)
        port.sync()
        yield port
        port.close()


def test_ready_once_after_boot_and_the_id(serve: type[FirmwareProcess]) -> None:
    """READY is the box's first line; opening the port does not reset a simulated box (no DTR
    wiring), so READY is still in the pty when the host opens it, or was flushed by the open."""
    box = serve("atmega328p")
    port = RawPort(box.port, baudrate=1_000_000)
    try:
        port.send(b"PING #1\n")
        first = port.line()
        assert first in ("READY trigbox-avr328p 1.1.0", "PONG #1")
        if first.startswith("READY"):
            assert port.line() == "PONG #1"
        assert port.cmd("ID?") == ["ID rigd trigbox-avr328p UNSET 1.1.0"]
    finally:
        port.close()
