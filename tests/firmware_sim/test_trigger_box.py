"""The simulated trigger-box firmware, spoken to with raw pyserial over its pty."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from uuid import uuid4

import numpy as np
import pytest

from drivers.testing.trigger_protocol import (
    LINE_RE,
    RawPort,
    TriggerProtocolContract,
    assert_next_is_pong,
    checksum,
    collect_run,
    pulses,
)
from firmware_sim.trigger_box import SimTriggerBox
from firmware_sim.trigger_commands import RING_SIZE
from firmware_sim.world import Edge, SimWorld, get_world, reset_world


def _world() -> SimWorld:
    return get_world(f"t-{uuid4().hex}")


@pytest.fixture
def world() -> Iterator[SimWorld]:
    w = _world()
    yield w
    reset_world(w.name)


def _open(world: SimWorld, **kw: object) -> tuple[SimTriggerBox, RawPort]:
    box = SimTriggerBox(world, boot_ms=kw.pop("boot_ms", 0), **kw)  # type: ignore[arg-type]
    port = RawPort(box.port_path)
    box.booted.wait(2.0)
    return box, port


class TestSimBoxProtocol(TriggerProtocolContract):
    """The protocol contract against the Python model of the box (its pty, raw pyserial)."""

    @pytest.fixture
    def port(self, world: SimWorld) -> Iterator[RawPort]:
        box, port = _open(world)
        port.sync()
        yield port
        port.close()
        box.close()


def test_ready_after_boot_and_input_ignored_while_booting(world: SimWorld) -> None:
    t_open = time.monotonic()
    box = SimTriggerBox(world, boot_ms=300)
    port = RawPort(box.port_path)
    try:
        port.send(b"PING #1\n")  # before boot: the UART is not listening yet
        assert port.line(timeout=2.0) == "READY trigbox-sim 1.0.0"
        assert time.monotonic() - t_open >= 0.29
        assert_next_is_pong(port, 2)  # the early PING got no reply (it would come first)
    finally:
        port.close()
        box.close()


def test_pulse_schedule_exact_and_start_n_stops_by_itself(world: SimWorld) -> None:
    box, port = _open(world, jitter_us=3.0, drift_ppm=40.0, offset_us=1_234_567)
    try:
        port.cmd("RATE 700")  # period 1428.57 us: exercises the rounding of k * 1e6 / rate
        port.cmd("WIDTH 200")
        port.cmd("ARM")
        t0 = int(port.cmd("START 60")[0].split()[2])
        run = collect_run(port, 60)
        assert port.cmd("STATUS?")[0].startswith("STATUS IDLE count=60")
        assert_next_is_pong(port)  # nothing after END (the run is over: no pulse line can follow)
        got = pulses(run)
        assert got == [(k, t0 + round(k * 1e6 / 700)) for k in range(60)]
        assert port.cmd("STATUS?")[0].startswith("STATUS IDLE count=60 target=60")
        truth = sorted(world.truth.pulses)
        assert [(k, b) for k, b, _, _ in truth] == got
        assert all(delivered for *_, delivered in truth)
    finally:
        port.close()
        box.close()


def test_drift_and_offset_follow_the_box_clock(world: SimWorld) -> None:
    drift_ppm, offset_us = 3000.0, 5_000_000.0
    box, port = _open(world, drift_ppm=drift_ppm, offset_us=offset_us)
    try:
        true_before = world.now_us()
        clock = int(port.cmd("CLOCK?")[0].split()[1])
        true_after = world.now_us()
        rate = 1 + drift_ppm * 1e-6
        assert offset_us + true_before * rate - 1 <= clock <= offset_us + true_after * rate
        port.cmd("RATE 1000")
        port.cmd("WIDTH 100")
        port.cmd("ARM")
        port.cmd("START 100")
        collect_run(port, 100)
        _, box_us, true_us, _ = (np.array(c, dtype=np.float64) for c in zip(*world.truth.pulses, strict=True))
        slope = np.polyfit(true_us - true_us[0], box_us - box_us[0], 1)[0]
        assert slope == pytest.approx(rate, abs=2e-6)
        # Box period is exactly 1000 box-us, so the true period is 1000 / rate.
        assert np.diff(true_us) == pytest.approx(1000 / rate, abs=1e-6)
    finally:
        port.close()
        box.close()


def test_jitter_is_gaussian_with_the_configured_sigma(world: SimWorld) -> None:
    box, port = _open(world, jitter_us=5.0, seed=3)
    try:
        port.cmd("RATE 5000")
        port.cmd("WIDTH 10")
        port.cmd("ARM")
        port.cmd("START 400")
        collect_run(port, 400)
        err = np.array([t - box.clock.true_at(b) for _, b, t, _ in world.truth.pulses])
        assert 4.0 < err.std() < 6.0
        assert abs(err.mean()) < 1.0
    finally:
        port.close()
        box.close()


def test_dropped_pulses_reported_but_not_on_the_wire(world: SimWorld) -> None:
    edges: list[Edge] = []
    lock = threading.Lock()

    def on_edge(edge: Edge) -> None:
        with lock:
            edges.append(edge)

    unsubscribe = world.wire.subscribe(on_edge)
    box, port = _open(world, drop_pulses=[2, 5])
    try:
        port.cmd("RATE 1000")
        port.cmd("WIDTH 300")
        port.cmd("ARM")
        port.cmd("START 8")
        run = collect_run(port, 8)
        assert [k for k, _ in pulses(run)] == list(range(8))
        with lock:
            rising = [e.pulse_index for e in edges if e.rising]
            falling = [e for e in edges if not e.rising]
        assert rising == [0, 1, 3, 4, 6, 7]
        assert [e.pulse_index for e in falling] == rising
        rise_t = {e.pulse_index: e.true_us for e in edges if e.rising}
        assert all(e.true_us - rise_t[e.pulse_index] == pytest.approx(300) for e in falling)
        assert [(k, d) for k, _, _, d in world.truth.pulses] == [(k, k not in (2, 5)) for k in range(8)]
    finally:
        unsubscribe()
        port.close()
        box.close()


def test_garbage_fault_corrupts_some_lines_only(world: SimWorld) -> None:
    box, port = _open(world, garbage_every=3, seed=1)
    try:
        port.send(b"\n")
        port.send(b"RATE 2000\nWIDTH 10\nARM\nSTART 60\n")
        deadline = time.monotonic() + 30.0  # wait for the run's end, not for a fixed time
        while box.count < 60 or box.state != "IDLE":
            assert time.monotonic() < deadline, (box.count, box.state)
            time.sleep(0.01)
        lines: list[str] = []
        for tag in range(100, 110):  # every line of the run is in before a PONG (it may be garbled)
            port.send(f"PING #{tag}\n".encode())
            try:
                while (line := port.line(timeout=1.0)) != f"PONG #{tag}":
                    lines.append(line)
                break
            except TimeoutError:
                continue
        else:
            raise AssertionError("no PONG got through")
        good = [k for k, _ in pulses(lines)]
        assert 30 < len(good) < 60  # about a third of the lines carry garbage, half of those stay readable
        assert good == sorted(good)
        assert port.bad_lines
        assert any(any(b > 0x7E for b in raw) for raw in port.bad_lines)
        # Garbage comes before '$': a line whose checksum verifies after it is intact.
        salvaged = 0
        for raw in port.bad_lines:
            m = LINE_RE.match(raw[raw.rfind(b"$") :]) if b"$" in raw else None
            if m and checksum(m.group(1)) == int(m.group(2), 16):
                salvaged += 1
        assert 0 < salvaged < len(port.bad_lines)
    finally:
        port.close()
        box.close()


def test_readback_ring_buffer_and_close_idempotent(world: SimWorld) -> None:
    box, port = _open(world)
    try:
        port.cmd("RATE 2000")
        port.cmd("WIDTH 10")
        port.cmd("ARM")
        t0 = int(port.cmd("START 70")[0].split()[2])
        collect_run(port, 70)
        got = port.cmd("TS? 0 64")
        assert got[-1] == "OK TS 64"
        assert got[:-1] == [f"T {k} {t0 + 500 * k}" for k in range(64)]
        assert RING_SIZE == 65536
        port.cmd("ARM")  # a new run forgets the old records
        assert port.cmd("TS? 0 1") == ["OK TS 0"]
    finally:
        port.close()
        box.close()
        box.close()
    assert box.closed
    assert not any(t.name.endswith(world.name) and t.is_alive() for t in threading.enumerate())
