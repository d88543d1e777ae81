"""The real trigger driver against the simulated box, over both transports.

Every protocol test runs twice: over serial (the box on a pty, pyserial) and over raw HID
(the box behind a fake hidapi device, 64-byte reports). Serial- or HID-only tests say so.
"""

from __future__ import annotations

import os
import re
import sys
import time
from collections.abc import Iterator
from uuid import uuid4

import numpy as np
import pytest

from drivers import trigger_link
from drivers.base import Capability
from drivers.registry import DeviceSpec, open_device
from drivers.serial_trigger import SerialTrigger, open_serial_trigger
from drivers.trigger_lines import TriggerBoxError
from drivers.trigger_link import HidTransport, TransportError, hid_payload, hid_report, parse_hid_address
from firmware_sim.box_devices import find_trigger_box, open_sim_trigger
from firmware_sim.hid_box import SIM_HID_PID, SIM_HID_VID, FakeHidApi, attach
from firmware_sim.trigger_box import SimTriggerBox
from firmware_sim.world import SimWorld, get_world, reset_world
from rigd.core.devices import PulseBatch
from rigd.core.errors import (
    BackendUnavailableError,
    ConfigError,
    DeviceError,
    DeviceTimeoutError,
    ProtocolError,
)
from rigd.core.host_clock import MONOTONIC
from rigd.core.settings import TriggerSettings


def _name() -> str:
    return f"t-{uuid4().hex}"


@pytest.fixture
def world_name() -> Iterator[str]:
    name = _name()
    yield name
    reset_world(name)


@pytest.fixture(params=["serial", "hid"])
def transport(request: pytest.FixtureRequest) -> str:
    """The link the protocol suite runs over."""
    return str(request.param)


def _spec(world_name: str, query: str = "", transport: str = "serial") -> str:
    if transport != "serial":
        query = f"{query}&transport={transport}" if query else f"transport={transport}"
    return f"sim://{world_name}/trigger?{query}" if query else f"sim://{world_name}/trigger"


def _open(
    world_name: str, query: str = "", transport: str = "serial"
) -> tuple[SerialTrigger, SimTriggerBox, SimWorld]:
    trig = open_sim_trigger(DeviceSpec.parse(_spec(world_name, query, transport)))
    world = get_world(world_name)
    box = find_trigger_box(world)
    assert box is not None
    return trig, box, world


def _run(trig: SerialTrigger, n: int, rate_hz: float = 1000.0, width_us: int = 100) -> tuple[int, PulseBatch]:
    trig.configure(TriggerSettings(rate_hz=rate_hz, pulse_width_us=width_us))
    trig.arm()
    t0 = trig.start(n)
    deadline = time.monotonic() + 30.0  # a state to wait for; generous for a loaded machine
    while trig.is_running():
        assert time.monotonic() < deadline, "the run never ended"
        time.sleep(0.01)
    parts = [trig.read_pulses(0.05)]
    while len(parts[-1]):
        parts.append(trig.read_pulses(0.01))
    batch = PulseBatch(
        np.concatenate([p.index for p in parts]),
        np.concatenate([p.t_us for p in parts]),
        np.concatenate([p.host_time_ns for p in parts]),
    )
    return t0, batch


def test_handshake_waits_for_boot_without_fixed_sleep(world_name: str, transport: str) -> None:
    t = time.monotonic()
    trig, box, _ = _open(world_name, "boot_ms=400", transport)
    took = time.monotonic() - t
    try:
        assert 0.39 <= took < 1.0  # answered as soon as the box booted, not after a fixed sleep
        assert trig.info.kind == "trigger"
        assert (trig.info.vendor, trig.info.model, trig.info.firmware) == ("rigd-sim", "trigbox-sim", "1.0.0")
        assert trig.info.spec == _spec(world_name, "boot_ms=400", transport)
        assert trig.capabilities == {Capability.PULSE_TIMESTAMPS, Capability.PULSE_COUNT}
    finally:
        trig.close()
    assert box.closed  # closing the trigger closes the sim box


def test_run_reports_every_pulse_with_box_timestamps(world_name: str, transport: str) -> None:
    trig, box, world = _open(world_name, "drift_ppm=12&jitter_us=2&offset_us=777", transport)
    try:
        t0, batch = _run(trig, 50)
        assert batch.index.tolist() == list(range(50))
        assert batch.t_us.tolist() == [t0 + 1000 * k for k in range(50)]
        assert [(k, b) for k, b, _, _ in world.truth.pulses] == list(
            zip(range(50), batch.t_us.tolist(), strict=True)
        )
        assert (np.diff(batch.host_time_ns) >= 0).all()
        assert trig.stop() == 50
        assert trig.pulse_count() == 50
        assert trig.stats["corrupt_lines"] == 0
        assert trig.stats["pulses_received"] == 50
        assert trig.missing_indices == []
        # The box clock is the rig clock: CLOCK? tracks the box's DeviceClock.
        assert abs(trig.clock_us() - box.box_now()) < 50_000
    finally:
        trig.close()
        trig.close()


def test_garbage_fault_counted_and_pulses_recovered(world_name: str, transport: str) -> None:
    trig, _, world = _open(world_name, "garbage_every=5&seed=4", transport)
    try:
        t0, batch = _run(trig, 150, rate_hz=1000.0)
        assert batch.index.tolist() == list(range(150))
        assert batch.t_us.tolist() == [t0 + 1000 * k for k in range(150)]
        stats = trig.stats
        assert stats["corrupt_lines"] > 0
        assert stats["garbage_bytes"] > 0
        assert stats["recovered_pulses"] > 0
        assert stats["unrecovered_pulses"] == 0
        assert stats["pulses_received"] + stats["recovered_pulses"] == 150
        assert [b for _, b, _, _ in world.truth.pulses] == batch.t_us.tolist()
    finally:
        trig.close()


@pytest.mark.slow
def test_unrecoverable_pulses_stay_visible(world_name: str, transport: str) -> None:
    trig, box, _ = _open(world_name, "garbage_every=3&seed=2", transport)
    try:
        trig.reply_timeout_s = 0.05
        trig.configure(TriggerSettings(rate_hz=2000.0, pulse_width_us=10))
        trig.arm()
        # The link is quiet once ARM is answered: count from here what the box sends and the
        # driver takes in (a line lost at the open, before the driver listened, is in neither).
        sent0, seen0 = box._lines_sent, trig.stats["lines"] + trig.stats["corrupt_lines"]
        trig.start(40)
        deadline = time.monotonic() + 30.0  # states to wait for, not fixed delays
        while box.count < 40 or box.state != "IDLE":
            assert time.monotonic() < deadline, (box.count, box.state)
            time.sleep(0.01)
        # Every line the box sent (END included) has reached the driver, good or corrupt.
        while trig.stats["lines"] + trig.stats["corrupt_lines"] - seen0 < box._lines_sent - sent0:
            assert time.monotonic() < deadline, (trig.stats, box._lines_sent, sent0, seen0)
            time.sleep(0.01)
        box.mute = True  # readback can no longer be answered
        batch = trig.read_pulses(0.1)
        got = batch.index.tolist()
        missing = trig.missing_indices
        assert missing, "the garbage fault should have cost some pulse records"
        assert sorted(got + missing) == list(range(max(got + missing) + 1))
        assert not set(got) & set(missing)
        assert trig.stats["unrecovered_pulses"] == len(missing)
        box.mute = False
    finally:
        trig.close()


def test_err_reply_raises_protocol_error(world_name: str, transport: str) -> None:
    trig, _, _ = _open(world_name, transport=transport)
    try:
        with pytest.raises(TriggerBoxError) as exc_info:
            trig.start(5)  # not ARMED
        err = exc_info.value
        assert isinstance(err, ProtocolError)
        assert err.code == "STATE"
        assert err.command == "START 5"
        assert trig.port in str(err)
        assert "START 5" in str(err)
        assert "ARMED" in str(err)
        with pytest.raises(ConfigError, match="shorter than the period"):
            trig.configure(TriggerSettings(rate_hz=1000.0, pulse_width_us=1000))
        with pytest.raises(ConfigError):
            trig.start(0)
        assert trig.pulse_count() == 0  # still usable after errors
    finally:
        trig.close()


def test_silent_port_times_out_naming_port_and_command() -> None:
    master, slave = os.openpty()
    port = os.ttyname(slave)
    try:
        t = time.monotonic()
        with pytest.raises(DeviceTimeoutError, match=rf"{port}.*PING"):
            SerialTrigger(port, boot_timeout_s=0.3)
        assert time.monotonic() - t < 2.0
    finally:
        os.close(master)
        os.close(slave)


def test_hung_box_times_out(world_name: str, transport: str) -> None:
    trig, box, _ = _open(world_name, transport=transport)
    try:
        trig.reply_timeout_s = 0.2
        box.mute = True
        with pytest.raises(DeviceTimeoutError, match=rf"{trig.port}.*COUNT\?.*0.2 s"):
            trig.pulse_count()
        box.mute = False
        assert trig.pulse_count() == 0
    finally:
        trig.close()


def test_box_gone_surfaces_as_device_error(world_name: str, transport: str) -> None:
    trig, box, _ = _open(world_name, transport=transport)
    try:
        box.close()
        trig.reply_timeout_s = 0.1
        with pytest.raises(DeviceError):
            trig.pulse_count()
    finally:
        trig.close()


def test_start_reply_lost_is_resolved_from_status(world_name: str, transport: str) -> None:
    trig, box, _ = _open(world_name, transport=transport)
    try:
        trig.reply_timeout_s = 0.2
        trig.configure(TriggerSettings(rate_hz=1000.0, pulse_width_us=10))
        trig.arm()
        box.drop_replies = 1  # the box starts, but its OK START never arrives
        t0 = trig.start(3)
        assert t0 == int(trig.status()["t0"])
        assert t0 > 0
        box.drop_replies = 1
        with pytest.raises(DeviceTimeoutError, match=r"'ARM' within 0.2 s"):
            trig.arm()  # no corrupt line seen: a lost reply is a timeout, not a retry
    finally:
        trig.close()


def test_sim_open_twice_in_one_world_is_refused(world_name: str, transport: str) -> None:
    trig, _, _ = _open(world_name, transport=transport)
    try:
        with pytest.raises(ConfigError, match="already has an open trigger box"):
            open_sim_trigger(DeviceSpec.parse(f"sim://{world_name}/trigger"))
        with pytest.raises(ConfigError, match="unknown parameter"):
            open_sim_trigger(DeviceSpec.parse(f"sim://{_name()}/trigger?jiter_us=2"))
    finally:
        trig.close()
    trig2, box2, _ = _open(world_name, transport=transport)  # a closed box is replaced by a fresh one
    trig2.close()
    assert box2.closed


def test_open_device_sim_through_entry_point(world_name: str) -> None:
    trig = open_device("trigger", f"sim://{world_name}/trigger?drift_ppm=12&jitter_us=2&seed=0")
    try:
        assert isinstance(trig, SerialTrigger)
        assert find_trigger_box(get_world(world_name)) is not None
        _, batch = _run(trig, 5)
        assert batch.index.tolist() == [0, 1, 2, 3, 4]
    finally:
        trig.close()


def test_open_serial_specs(world_name: str) -> None:
    box = SimTriggerBox(get_world(world_name), boot_ms=0)
    try:
        for spec in (box.port_path, f"serial://{box.port_path}?baud=921600&reply_timeout_s=0.5"):
            trig = open_device("trigger", spec)
            try:
                assert isinstance(trig, SerialTrigger)
                assert trig.info.spec == spec  # (generous reply timeout: CI machines are shared)
                assert trig.pulse_count() == 0
            finally:
                trig.close()
        assert not box.closed  # a real port: closing the driver leaves the box alone
        with pytest.raises(ConfigError, match="unknown parameter"):
            open_serial_trigger(DeviceSpec.parse(f"serial://{box.port_path}?speed=9600"))
        with pytest.raises(DeviceError, match="cannot open"):
            open_device("trigger", "/dev/does-not-exist-rigd")
    finally:
        box.close()


def test_unplug_mid_run_is_reported_not_a_crash(world_name: str, transport: str) -> None:
    trig, box, _ = _open(world_name, transport=transport)
    try:
        trig.configure(TriggerSettings(rate_hz=1000.0, pulse_width_us=100))
        trig.arm()
        trig.start()
        assert len(trig.read_pulses(0.5)) > 0
        box.close()  # the cable is pulled: the link goes away under the reader thread
        deadline = time.monotonic() + 30.0  # ends at the error; the bound only stops a hang
        with pytest.raises(TransportError, match=rf"{re.escape(trig.port)} disconnected"):  # noqa: PT012
            while time.monotonic() < deadline:
                trig.read_pulses(0.05)
        with pytest.raises(DeviceError, match="disconnected"):
            trig.pulse_count()
    finally:
        trig.close()  # no STOP to a box that is gone, no exception
    trig.close()


# ---------------------------------------------------------------- HID only
def test_hid_report_framing() -> None:
    assert hid_report(b"PING #1*2E\n") == bytes([11]) + b"PING #1*2E\n" + bytes(52)
    assert len(hid_report(b"x" * 63)) == 64
    with pytest.raises(ValueError, match="at most 63"):
        hid_report(b"x" * 64)
    assert hid_payload(hid_report(b"abc")) == b"abc"
    assert hid_payload(bytes([64]) + bytes(63)) is None  # impossible length byte
    assert hid_payload(b"") == b""


class _RecordingHid:
    def __init__(self, reports: list[bytes]) -> None:
        self.written: list[bytes] = []
        self.reports = reports
        self.closed = 0

    def read(self, max_length: int, timeout_ms: int = 0) -> list[int]:
        return list(self.reports.pop(0)) if self.reports else []

    def write(self, buff: bytes | list[int]) -> int:
        self.written.append(bytes(buff))
        return len(buff)

    def close(self) -> None:
        self.closed += 1


def test_hid_transport_splits_long_writes_and_drops_bad_reports() -> None:
    dev = _RecordingHid([hid_report(b"$PONG"), bytes([200]) + bytes(63), hid_report(b"*50\n")])
    link = HidTransport(dev, "hid://1209:0001/X")
    link.write(b"A" * 100)
    assert [len(r) for r in dev.written] == [65, 65]  # report ID 0 + 64 bytes, twice
    assert all(r[0] == 0 for r in dev.written)
    assert dev.written[0][1] == 63
    assert dev.written[1][1] == 37
    assert b"".join(r[2 : 2 + r[1]] for r in dev.written) == b"A" * 100
    assert link.read(0.01) == b"$PONG"
    assert link.read(0.01) == b""  # length byte 200: dropped, counted
    assert link.bad_reports == 1
    assert link.read(0.01) == b"*50\n"
    assert link.read(0.01) == b""
    link.close()
    link.close()
    assert dev.closed == 1
    with pytest.raises(TransportError, match="closed"):
        link.read(0.01)


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        ("hid://16c0:0486", (0x16C0, 0x0486, None)),
        ("hid://16C0:0486/ABC123", (0x16C0, 0x0486, "ABC123")),
        ("hid://1209:0001/SIM0000?reply_timeout_s=2", (0x1209, 0x0001, "SIM0000")),
    ],
)
def test_hid_address_parsing(spec: str, expected: tuple[int, int, str | None]) -> None:
    assert parse_hid_address(DeviceSpec.parse(spec)) == expected


@pytest.mark.parametrize("spec", ["hid://16c0", "hid://xyz:0486", "hid://16c0:10000", "hid:///dev/hidraw0"])
def test_hid_address_errors_name_the_spec(spec: str) -> None:
    with pytest.raises(ConfigError, match=re.escape(spec)):
        parse_hid_address(DeviceSpec.parse(spec))


def test_open_hid_spec_through_registry(world_name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """`hid://VID:PID/SERIAL` through open_device, with the fake hidapi module in place of `hid`."""
    monkeypatch.setattr(trigger_link, "_import_hid", lambda: FakeHidApi)
    box = SimTriggerBox(get_world(world_name), boot_ms=0, seed=7, link="socket")
    try:
        attach(box)
        spec = f"hid://{SIM_HID_VID:04x}:{SIM_HID_PID:04x}/SIM0007?reply_timeout_s=2"
        trig = open_device("trigger", spec)
        try:
            assert isinstance(trig, SerialTrigger)
            assert trig.info.spec == spec  # (generous reply timeout: CI machines are shared)
            assert trig.info.serial == "SIM0007"
            assert trig.port == "hid://1209:0001/SIM0007"
            _, batch = _run(trig, 5)
            assert batch.index.tolist() == [0, 1, 2, 3, 4]
        finally:
            trig.close()
        assert not box.closed  # a real device: closing the driver leaves the box alone
        with pytest.raises(DeviceError, match=r"hid://1209:0001/NOPE.*serial numbers present: SIM0007"):
            open_device("trigger", "hid://1209:0001/NOPE")
        with pytest.raises(DeviceError, match=r"hid://16c0:0486: no such HID device.*plugged in"):
            open_device("trigger", "hid://16c0:0486")
        with pytest.raises(ConfigError, match="unknown parameter"):
            open_device("trigger", "hid://1209:0001?baud=9600")
    finally:
        box.close()


def test_hid_without_hidapi_says_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "hid", None)  # makes `import hid` raise ImportError
    with pytest.raises(BackendUnavailableError, match="pip install hidapi"):
        open_device("trigger", "hid://16c0:0486")


def test_handshake_flush_line_draws_no_error_reply(world_name: str) -> None:
    """The newline the handshake sends first must not earn an ERR that a later command
    could take for its own reply (seen as `'ID?' failed: ERR UNKNOWN empty command`)."""
    box = SimTriggerBox(get_world(world_name), boot_ms=0, seed=3)
    try:
        for _ in range(10):
            trig = SerialTrigger(box.port_path, reply_timeout_s=2.0)
            try:
                assert trig.info.serial  # ID? answered by its own reply, not by an ERR
                assert trig.pulse_count() == 0
            finally:
                trig.close()
        assert box.errors_sent == []  # the flush newline is ignored, never an empty command
    finally:
        box.close()


class _StepClock:
    """A host clock far from the monotonic one that moves 1 us per reading."""

    def __init__(self) -> None:
        self.readings: list[int] = []
        self._next = 10**15

    def now_ns(self) -> int:
        self._next += 1000
        self.readings.append(self._next)
        return self._next


def test_records_are_stamped_with_the_injected_host_clock(world_name: str, transport: str) -> None:
    """The driver stamps every pulse record (read live or read back after line noise) with the
    host clock it was given, here the world's (`box_devices` hands it over), never its own."""
    world = get_world(world_name)
    clock = _StepClock()
    world.host_clock = clock
    trig, _, _ = _open(world_name, "garbage_every=5&seed=4", transport)
    try:
        assert trig.host_clock is clock
        _, batch = _run(trig, 60)
        assert batch.index.tolist() == list(range(60))
        assert trig.stats["recovered_pulses"] > 0  # some came by readback
        assert set(batch.host_time_ns.tolist()) <= set(clock.readings)
    finally:
        trig.close()


def test_a_serial_trigger_defaults_to_the_monotonic_clock(world_name: str) -> None:
    trig, _, _ = _open(world_name)
    try:
        assert trig.host_clock is MONOTONIC
        before = time.monotonic_ns()
        _, batch = _run(trig, 5)
        assert (batch.host_time_ns >= before).all()
        assert (batch.host_time_ns <= time.monotonic_ns()).all()
    finally:
        trig.close()
