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
        # Opened before the AVR runs a cycle: pyserial's open flushes the input queue, so a port
        # opened while the boot banner goes out would keep only its tail.
        with serial.Serial(harness.port_path, baudrate=1_000_000, timeout=5) as port:
            free.start()
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
        banner, answers = got.split(b"\n", 1)
        assert banner.startswith(b"$READY"), got
        return out[0].cycle, answers
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
        # Opened before the AVR runs a cycle: pyserial's open flushes the input queue, so a port
        # opened after the banner went out would lose it.
        with serial.Serial(harness.port_path, baudrate=1_000_000, timeout=5) as port:
            free.start()
            assert port.readline().startswith(b"$READY")
            harness.interrupt()
            free.join(60)
        assert out[0].quiet
        assert out[0].cycle < 65536 * 8  # READY is out long before Timer1's first overflow
    finally:
        harness.close()
