"""The firmware's timing, measured cycle by cycle under simavr with rigd's own driver on the
pty: every reported b_k is the documented schedule and the time of its rising edge, every
width is exact, nothing drifts, and records the line cannot carry arrive through TS?."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.registry import open_device
from drivers.serial_trigger import SerialTrigger
from drivers.testing.trigger import collect
from drivers.testing.trigger_protocol import schedule
from firmware_sim.testing.avr_box import CYCLES_PER_US, FirmwareProcess, PinChange
from rigd.core.devices import PulseBatch
from rigd.core.settings import TriggerSettings

TICK_CYCLES = 8  # Timer1 at 16 MHz / 8


def _open(box: FirmwareProcess) -> SerialTrigger:
    trig = open_device("trigger", f"serial://{box.port}?baud=1000000&reply_timeout_s=5")
    assert isinstance(trig, SerialTrigger)
    return trig


def _edges(box: FirmwareProcess, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Cycles of the first n rising and falling edges of the trigger pin (after the boot level)."""
    changes = box.wait_for_changes(2 * n + 1)
    while changes and changes[0].value == 0:  # the pin's level at boot, before any pulse
        changes = changes[1:]
    rises = np.array([c.cycle for c in changes if c.value == 1], dtype=np.int64)
    falls = np.array([c.cycle for c in changes if c.value == 0], dtype=np.int64)
    return rises[:n], falls[:n]


def _check_edges(rises: np.ndarray, falls: np.ndarray, b: np.ndarray, width_us: int) -> None:
    """Each rising edge within one timer tick of 16 * b_k cycles, each width exact to a tick."""
    late = rises - b * CYCLES_PER_US
    assert late.min() >= 0, f"an edge left before its b_k: {late.min()} cycles"
    assert late.max() < TICK_CYCLES, f"an edge left {late.max()} cycles after its b_k"
    widths = falls - rises
    assert np.abs(widths - width_us * CYCLES_PER_US).max() < TICK_CYCLES


def _run(
    trig: SerialTrigger, rate_hz: float, width_us: int, n: int, timeout_s: float
) -> tuple[int, PulseBatch]:
    """Configure, arm, `START n` and collect the records: the run's t0 and what arrived."""
    trig.configure(TriggerSettings(rate_hz=rate_hz, pulse_width_us=width_us))
    trig.arm()
    t0 = trig.start(n)
    return t0, collect(trig, n, timeout_s=timeout_s)


@pytest.mark.slow
def test_1khz_5000_pulses_each_at_its_reported_time(serve: type[FirmwareProcess]) -> None:
    box = serve("atmega328p")
    trig = _open(box)
    try:
        t0, batch = _run(trig, 1000.0, 100, 5000, timeout_s=60.0)
        assert trig.stop() == 5000
        assert batch.index.tolist() == list(range(5000))
        expected = np.array([schedule(t0, 1_000_000_000, k) for k in range(5000)])
        assert np.array_equal(batch.t_us, expected)
        assert trig.stats["recovered_pulses"] == 0  # 1 kHz fits the line: every record live
        rises, falls = _edges(box, 5000)
        assert len(rises) == len(falls) == 5000
        _check_edges(rises, falls, batch.t_us, 100)
    finally:
        trig.close()


@pytest.mark.slow
def test_30hz_for_ten_minutes_of_firmware_time_no_drift_no_lost_record(serve: type[FirmwareProcess]) -> None:
    """18000 pulses: firmware time runs as fast as simavr can (`--clock max`)."""
    box = serve("atmega328p", clock="max")
    trig = _open(box)
    try:
        t0, batch = _run(trig, 30.0, 1000, 18000, timeout_s=300.0)
        assert batch.index.tolist() == list(range(18000))
        expected = np.array([schedule(t0, 30_000_000, k) for k in range(18000)])
        assert np.array_equal(batch.t_us, expected)
        assert expected[-1] - t0 == 599_966_667  # 10 minutes of box time, to the microsecond
        assert trig.stats["recovered_pulses"] == 0
        rises, falls = _edges(box, 18000)
        _check_edges(rises, falls, batch.t_us, 1000)
    finally:
        trig.close()


@pytest.mark.slow
def test_10khz_records_the_line_cannot_carry_arrive_through_ts(serve: type[FirmwareProcess]) -> None:
    box = serve("atmega328p", clock="max")
    trig = _open(box)
    try:
        t0, batch = _run(trig, 10_000.0, 20, 5000, timeout_s=120.0)
        trig.stop()
        assert batch.index.tolist() == list(range(5000)), "a pulse record is missing"
        assert np.array_equal(batch.t_us, t0 + 100 * np.arange(5000))
        stats = trig.stats
        assert stats["unrecovered_pulses"] == 0
        diag = trig.diag()
        dropped = diag["records_dropped"]
        assert dropped > 1000, "10 kHz should not fit a 1 Mbaud line"
        assert stats["recovered_pulses"] == dropped  # every record not sent live came by TS?
        assert diag["late_edges"] == 0
        rises, falls = _edges(box, 5000)
        _check_edges(rises, falls, batch.t_us, 20)
    finally:
        trig.close()


def test_edges_file_lines(serve: type[FirmwareProcess]) -> None:
    """`<cycle> <pin-name> <0|1>`, cycles increasing."""
    box = serve("atmega328p")
    trig = _open(box)
    try:
        trig.configure(TriggerSettings(rate_hz=500.0, pulse_width_us=50))
        trig.arm()
        trig.start(3)
        collect(trig, 3)
        changes = box.wait_for_changes(7)
        levels = [c.value for c in changes]
        assert levels[levels.index(1) :][:6] == [1, 0, 1, 0, 1, 0]
        cycles = [c.cycle for c in changes]
        assert cycles == sorted(cycles)
        assert all(isinstance(c, PinChange) and c.pin == "TRIG" for c in changes)
    finally:
        trig.close()
