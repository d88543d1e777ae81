"""The real serial trigger driver against the simulated box on a pty."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from uuid import uuid4

import numpy as np
import pytest

from drivers.base import Capability, PulseBatch, TriggerSettings
from drivers.registry import DeviceSpec, open_device
from drivers.serial_trigger import SerialTrigger, TriggerBoxError, open_serial_trigger
from firmware_sim.trigger_box import SimTriggerBox, find_trigger_box, open_sim_trigger
from firmware_sim.world import SimWorld, get_world, reset_world
from rigd.core.errors import ConfigError, DeviceError, DeviceTimeoutError, ProtocolError


def _name() -> str:
    return f"t-{uuid4().hex}"


@pytest.fixture
def world_name() -> Iterator[str]:
    name = _name()
    yield name
    reset_world(name)


def _open(world_name: str, query: str = "") -> tuple[SerialTrigger, SimTriggerBox, SimWorld]:
    trig = open_sim_trigger(
        DeviceSpec.parse(f"sim://{world_name}/trigger?{query}" if query else f"sim://{world_name}/trigger")
    )
    world = get_world(world_name)
    box = find_trigger_box(world)
    assert box is not None
    return trig, box, world


def _run(trig: SerialTrigger, n: int, rate_hz: float = 1000.0, width_us: int = 100) -> tuple[int, PulseBatch]:
    trig.configure(TriggerSettings(rate_hz=rate_hz, pulse_width_us=width_us))
    trig.arm()
    t0 = trig.start(n)
    deadline = time.monotonic() + 5.0
    while trig.is_running():
        assert time.monotonic() < deadline
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


def test_handshake_waits_for_boot_without_fixed_sleep(world_name: str) -> None:
    t = time.monotonic()
    trig, box, _ = _open(world_name, "boot_ms=400")
    took = time.monotonic() - t
    try:
        assert 0.39 <= took < 1.0  # answered as soon as the box booted, not after a fixed sleep
        assert trig.info.kind == "trigger"
        assert (trig.info.vendor, trig.info.model, trig.info.firmware) == ("rigd-sim", "trigbox-sim", "1.0.0")
        assert trig.info.spec == f"sim://{world_name}/trigger?boot_ms=400"
        assert trig.capabilities == {Capability.PULSE_TIMESTAMPS, Capability.PULSE_COUNT}
    finally:
        trig.close()
    assert box.closed  # closing the trigger closes the sim box


def test_run_reports_every_pulse_with_box_timestamps(world_name: str) -> None:
    trig, box, world = _open(world_name, "drift_ppm=12&jitter_us=2&offset_us=777")
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


def test_garbage_fault_counted_and_pulses_recovered(world_name: str) -> None:
    trig, _, world = _open(world_name, "garbage_every=5&seed=4")
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


def test_unrecoverable_pulses_stay_visible(world_name: str) -> None:
    trig, box, _ = _open(world_name, "garbage_every=3&seed=2")
    try:
        trig.reply_timeout_s = 0.05
        trig.configure(TriggerSettings(rate_hz=2000.0, pulse_width_us=10))
        trig.arm()
        trig.start(40)
        deadline = time.monotonic() + 3.0
        while box.count < 40 and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.05)
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


def test_err_reply_raises_protocol_error(world_name: str) -> None:
    trig, _, _ = _open(world_name)
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


def test_hung_box_times_out(world_name: str) -> None:
    trig, box, _ = _open(world_name)
    try:
        trig.reply_timeout_s = 0.2
        box.mute = True
        with pytest.raises(DeviceTimeoutError, match=rf"{trig.port}.*COUNT\?.*0.2 s"):
            trig.pulse_count()
        box.mute = False
        assert trig.pulse_count() == 0
    finally:
        trig.close()


def test_box_gone_surfaces_as_device_error(world_name: str) -> None:
    trig, box, _ = _open(world_name)
    try:
        box.close()
        trig.reply_timeout_s = 0.1
        with pytest.raises(DeviceError):
            trig.pulse_count()
    finally:
        trig.close()


def test_start_reply_lost_is_resolved_from_status(world_name: str) -> None:
    trig, box, _ = _open(world_name)
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


def test_sim_open_twice_in_one_world_is_refused(world_name: str) -> None:
    trig, _, _ = _open(world_name)
    try:
        with pytest.raises(ConfigError, match="already has an open trigger box"):
            open_sim_trigger(DeviceSpec.parse(f"sim://{world_name}/trigger"))
        with pytest.raises(ConfigError, match="unknown parameter"):
            open_sim_trigger(DeviceSpec.parse(f"sim://{_name()}/trigger?jiter_us=2"))
    finally:
        trig.close()
    trig2, box2, _ = _open(world_name)  # a closed box is replaced by a fresh one
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
                assert trig.info.spec == spec
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
