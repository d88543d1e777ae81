"""The firmware's clock on the virtual clock depends on the host's commands alone: FREE hands
it one host line at a time, each when it is idle, and stops exactly where it goes idle."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import serial

from firmware_sim.avr.harness import AvrHarness, Step

COMMANDS = b"\nPING #1\nRATE 30\nWIDTH 1000\nARM\nSTART 3\n"


def _start_cycle(elf: Path, chunks: list[bytes]) -> tuple[int, bytes]:
    """The AVR cycle at which START scheduled the first edge, and what the box sent."""
    harness = AvrHarness(elf, mcu="atmega328p", clock="control", free_lines=True)
    try:
        out: list[Step] = []
        free = threading.Thread(target=lambda: out.append(harness.free()))
        free.start()
        with serial.Serial(harness.port_path, baudrate=1_000_000, timeout=5) as port:
            for chunk in chunks:
                port.write(chunk)
                time.sleep(0.05)  # the host's own pace: it must not reach the firmware's clock
            free.join(60)
            assert out, "FREE did not return when START scheduled the first edge"
            assert not out[0].quiet
            harness.run_until(out[0].cycle + 16_000 * 5)  # 5 ms: the reply to START goes out
            got = b""
            while b"OK START" not in got or not got.endswith(b"\n"):
                chunk = port.read(256)
                assert chunk, got
                got += chunk
        # The boot banner goes out before any host input, so whether the port was open in time
        # to catch it is the host's timing; everything after it answers the commands.
        if got.startswith(b"$READY"):
            got = got.split(b"\n", 1)[1]
        return out[0].cycle, got
    finally:
        harness.close()


def test_the_firmware_clock_at_start_does_not_depend_on_the_host_timing(
    firmware_build: Path, harness_binary: Path
) -> None:
    elf = firmware_build / "trigger_box_atmega328p.elf"
    whole = _start_cycle(elf, [COMMANDS])
    bytewise = _start_cycle(elf, [COMMANDS[i : i + 3] for i in range(0, len(COMMANDS), 3)])
    assert whole == bytewise
    assert b"OK START 2" in whole[1]  # t0 = the clock at START (a few ms) + 20000 us


def test_free_stops_where_the_firmware_went_idle(firmware_build: Path, harness_binary: Path) -> None:
    """Not one timer overflow later (an idle CPU's sleep jumps to the next timer event)."""
    elf = firmware_build / "trigger_box_atmega328p.elf"
    harness = AvrHarness(elf, mcu="atmega328p", clock="control", free_lines=True)
    try:
        out: list[Step] = []
        free = threading.Thread(target=lambda: out.append(harness.free()))
        free.start()
        with serial.Serial(harness.port_path, baudrate=1_000_000, timeout=5) as port:
            assert port.readline().startswith(b"$READY")
            harness.interrupt()
            free.join(60)
        assert out[0].quiet
        assert out[0].cycle < 65536 * 8  # READY is out long before Timer1's first overflow
    finally:
        harness.close()
