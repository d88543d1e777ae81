"""The simulated trigger-box firmware, spoken to with raw pyserial over its pty."""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Iterator
from uuid import uuid4

import numpy as np
import pytest
import serial
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware_sim.trigger_box import RING_SIZE, START_LEAD_US, SimTriggerBox, checksum
from firmware_sim.world import Edge, SimWorld, get_world, reset_world

_LINE_RE = re.compile(rb"^\$([ -~]*)\*([0-9A-F]{2})$")


class RawPort:
    """Minimal host side: framed lines in, checksummed lines out, no driver logic."""

    def __init__(self, path: str) -> None:
        self.ser = serial.serial_for_url(path, baudrate=115200, timeout=0.05)
        self.buf = bytearray()
        self.bad_lines: list[bytes] = []

    def send(self, data: bytes) -> None:
        self.ser.write(data)

    def raw_line(self, timeout: float = 2.0) -> bytes:
        deadline = time.monotonic() + timeout
        while b"\n" not in self.buf:
            if time.monotonic() > deadline:
                raise TimeoutError(f"no line within {timeout} s (buffer {bytes(self.buf)!r})")
            self.buf.extend(self.ser.read(max(1, self.ser.in_waiting)))
        nl = self.buf.index(b"\n")
        line = bytes(self.buf[:nl])
        del self.buf[: nl + 1]
        return line

    def line(self, timeout: float = 2.0) -> str:
        """Next line whose checksum verifies; corrupt ones go to `bad_lines`."""
        deadline = time.monotonic() + timeout
        while True:
            raw = self.raw_line(max(0.0, deadline - time.monotonic()))
            m = _LINE_RE.match(raw)
            if m and checksum(m.group(1)) == int(m.group(2), 16):
                return m.group(1).decode()
            self.bad_lines.append(raw)

    def cmd(self, text: str, tag: int = 7) -> list[str]:
        """Send `text #tag`, return the tagged reply lines (T lines then the final line)."""
        self.send(f"{text} #{tag}\n".encode())
        out: list[str] = []
        while True:
            line = self.line()
            if line.endswith(f" #{tag}"):
                out.append(line[: -len(f" #{tag}")])
                if not line.startswith("T "):
                    return out

    def close(self) -> None:
        self.ser.close()


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


@pytest.fixture
def rig(world: SimWorld) -> Iterator[tuple[SimTriggerBox, RawPort]]:
    box, port = _open(world)
    port.cmd("PING")  # sync: READY may or may not have been flushed by the open
    yield box, port
    port.close()
    box.close()


def assert_next_is_pong(port: RawPort, tag: int = 99) -> None:
    """The box answers in order: the next line after a PING is its PONG when nothing else is
    pending (a check that no line is left over, instead of watching the port for a while)."""
    port.send(f"PING #{tag}\n".encode())
    assert port.line() == f"PONG #{tag}"


def _pulses(lines: list[str]) -> list[tuple[int, int]]:
    return [(int(f[1]), int(f[2])) for f in (ln.split() for ln in lines) if f[0] == "P"]


def _collect_run(port: RawPort, n: int, timeout: float = 5.0) -> list[str]:
    """Lines up to and including `END n`."""
    out: list[str] = []
    deadline = time.monotonic() + timeout
    while True:
        line = port.line(max(0.0, deadline - time.monotonic()))
        out.append(line)
        if line == f"END {n}":
            return out


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


def test_every_command(rig: tuple[SimTriggerBox, RawPort]) -> None:
    box, port = rig
    assert port.cmd("PING") == ["PONG"]
    assert port.cmd("ID?") == ["ID rigd-sim trigbox-sim SIM0000 1.0.0"]
    assert port.cmd("rate 500") == ["OK RATE 500.000000"]  # commands are case-insensitive
    assert port.cmd("WIDTH 100") == ["OK WIDTH 100"]
    assert port.cmd("STATUS?") == ["STATUS IDLE count=0 target=0 rate=500.000000 width=100 t0=-1"]
    assert port.cmd("ARM") == ["OK ARM"]
    assert port.cmd("STATUS?")[0].startswith("STATUS ARMED count=0")
    assert port.cmd("COUNT?") == ["COUNT 0"]
    before = box.box_now()
    clock = int(port.cmd("CLOCK?")[0].split()[1])
    assert before <= clock <= box.box_now()
    reply = port.cmd("START 5")[0].split()
    assert reply[:2] == ["OK", "START"]
    assert reply[3] == "5"
    t0 = int(reply[2])
    assert clock + START_LEAD_US <= t0 <= box.box_now() + START_LEAD_US
    run = _collect_run(port, 5)
    assert _pulses(run) == [(k, t0 + 2000 * k) for k in range(5)]
    assert port.cmd("COUNT?") == ["COUNT 5"]
    assert port.cmd("STATUS?") == [f"STATUS IDLE count=5 target=5 rate=500.000000 width=100 t0={t0}"]
    assert port.cmd("TS? 1 3") == [f"T {k} {t0 + 2000 * k}" for k in (1, 2, 3)] + ["OK TS 3"]
    assert port.cmd("TS? 3 10") == [f"T {k} {t0 + 2000 * k}" for k in (3, 4)] + ["OK TS 2"]
    assert port.cmd("TS? 9 1") == ["OK TS 0"]
    assert port.cmd("STOP") == ["OK STOP 5"]
    # A checksummed command line is accepted; '$' in front is optional.
    payload = b"PING #9"
    port.send(b"$" + payload + b"*%02X\r\n" % checksum(payload))
    assert port.line() == "PONG #9"


@pytest.mark.parametrize(
    ("line", "code"),
    [
        (b"FOO", "UNKNOWN"),
        (b"#5", "UNKNOWN"),
        (b"PING extra", "BADARG"),
        (b"RATE", "BADARG"),
        (b"RATE abc", "BADARG"),
        (b"RATE nan", "BADARG"),
        (b"RATE 1e3", "BADARG"),
        (b"RATE 0", "BADARG"),
        (b"RATE 10000.5", "BADARG"),
        (b"RATE -5", "BADARG"),
        (b"WIDTH 0", "BADARG"),
        (b"WIDTH 1.5", "BADARG"),
        (b"WIDTH 1000001", "BADARG"),
        (b"START 0", "BADARG"),
        (b"START x", "BADARG"),
        (b"TS? 0", "BADARG"),
        (b"TS? 0 0", "BADARG"),
        (b"TS? 0 65", "BADARG"),
        (b"TS? -1 2", "BADARG"),
        (b"PING #99999", "BADARG"),
        (b"START", "STATE"),
        (b"PING*00", "CHECKSUM"),
        (b"PING*G1", "CHECKSUM"),
        (b"X" * 65, "TOOLONG"),
        (b"PI\xffNG", "BADCHAR"),
        (b"PI\tNG", "BADCHAR"),
    ],
)
def test_bad_lines_get_err(rig: tuple[SimTriggerBox, RawPort], line: bytes, code: str) -> None:
    _, port = rig
    port.send(line + b"\n")
    reply = port.line().split()
    assert reply[:2] == ["ERR", code], reply
    assert port.cmd("PING") == ["PONG"]  # and the box keeps working


def test_err_echoes_the_tag(rig: tuple[SimTriggerBox, RawPort]) -> None:
    _, port = rig
    assert port.cmd("RATE fast", tag=42)[0].startswith("ERR BADARG rate 'fast'")


def test_wrong_state(rig: tuple[SimTriggerBox, RawPort]) -> None:
    _, port = rig
    port.cmd("RATE 1000")
    port.cmd("WIDTH 10")
    assert port.cmd("START 5")[0].startswith("ERR STATE START needs ARMED, box is IDLE")
    port.cmd("ARM")
    assert port.cmd("START")[0].startswith("OK START")
    for cmd in ("RATE 10", "WIDTH 5", "ARM", "START", "START 3"):
        assert port.cmd(cmd)[0].startswith("ERR STATE"), cmd
    assert port.cmd("PING") == ["PONG"]
    assert port.cmd("STOP")[0].startswith("OK STOP")
    assert port.cmd("STOP")[0].startswith("OK STOP")  # STOP is allowed in every state
    assert port.cmd("START")[0].startswith("ERR STATE")  # needs a new ARM


def test_width_must_be_shorter_than_period(rig: tuple[SimTriggerBox, RawPort]) -> None:
    _, port = rig
    port.cmd("RATE 1000")
    port.cmd("WIDTH 1000")
    port.cmd("ARM")
    assert port.cmd("START 3")[0] == "ERR BADARG width 1000 us >= period 1000.0 us"


@pytest.fixture(scope="module")
def shared_rig() -> Iterator[tuple[SimTriggerBox, RawPort]]:
    w = _world()
    box, port = _open(w)
    port.cmd("PING")
    yield box, port
    port.close()
    box.close()
    reset_world(w.name)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(garbage=st.binary(min_size=1, max_size=200).filter(lambda b: b"\n" not in b))
def test_random_garbage_gets_err_and_box_survives(
    shared_rig: tuple[SimTriggerBox, RawPort], garbage: bytes
) -> None:
    _, port = shared_rig
    has_bad_byte = any(not 0x20 <= b <= 0x7E for b in garbage.rstrip(b"\r"))
    port.send(garbage + b"\n")
    port.send(b"PING #77\n")
    replies: list[str] = []
    while (line := port.line()) != "PONG #77":
        replies.append(line)
    assert all(r.startswith("ERR ") for r in replies), replies
    if has_bad_byte or len(garbage.rstrip(b"\r")) > 64:
        assert len(replies) == 1
        assert replies[0].split()[1] in ("BADCHAR", "TOOLONG")


def test_overlong_line_one_err_even_in_pieces(rig: tuple[SimTriggerBox, RawPort]) -> None:
    _, port = rig
    port.send(b"A" * 100)
    # Real time on purpose: a pause on the link, so the line reaches the box in pieces.
    time.sleep(0.02)
    port.send(b"B" * 5000 + b"\n")
    assert port.line() == "ERR TOOLONG line exceeds 64 bytes"
    assert_next_is_pong(port)  # no second ERR: the box answers in order, so it would come first
    port.send(b"P" * 64 + b"\n")  # exactly at the limit: parsed, unknown
    assert port.line().startswith("ERR UNKNOWN")


def test_pulse_schedule_exact_and_start_n_stops_by_itself(world: SimWorld) -> None:
    box, port = _open(world, jitter_us=3.0, drift_ppm=40.0, offset_us=1_234_567)
    try:
        port.cmd("RATE 700")  # period 1428.57 us: exercises the rounding of k * 1e6 / rate
        port.cmd("WIDTH 200")
        port.cmd("ARM")
        t0 = int(port.cmd("START 60")[0].split()[2])
        run = _collect_run(port, 60)
        assert port.cmd("STATUS?")[0].startswith("STATUS IDLE count=60")
        assert_next_is_pong(port)  # nothing after END (the run is over: no pulse line can follow)
        pulses = _pulses(run)
        assert pulses == [(k, t0 + round(k * 1e6 / 700)) for k in range(60)]
        assert port.cmd("STATUS?")[0].startswith("STATUS IDLE count=60 target=60")
        truth = sorted(world.truth.pulses)
        assert [(k, b) for k, b, _, _ in truth] == pulses
        assert all(delivered for *_, delivered in truth)
    finally:
        port.close()
        box.close()


def test_start_then_stop(rig: tuple[SimTriggerBox, RawPort]) -> None:
    box, port = rig
    port.cmd("RATE 1000")
    port.cmd("WIDTH 100")
    port.cmd("ARM")
    port.cmd("START")
    lines: list[str] = []
    while len(_pulses(lines)) <= 30:  # wait for 31 pulses, not for a fixed time
        lines.append(port.line())
    port.send(b"STOP #3\n")
    while not (line := port.line()).endswith("#3"):
        lines.append(line)
    count = int(line.split()[2])
    assert count > 30
    assert [k for k, _ in _pulses(lines)] == list(range(count))  # every pulse reported before OK STOP
    assert_next_is_pong(port)  # the box is stopped: nothing after OK STOP
    assert box.state == "IDLE"


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
        _collect_run(port, 100)
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
        _collect_run(port, 400)
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
        run = _collect_run(port, 8)
        assert [k for k, _ in _pulses(run)] == list(range(8))
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
        good = [k for k, _ in _pulses(lines)]
        assert 30 < len(good) < 60  # about a third of the lines carry garbage, half of those stay readable
        assert good == sorted(good)
        assert port.bad_lines
        assert any(any(b > 0x7E for b in raw) for raw in port.bad_lines)
        # Garbage comes before '$': a line whose checksum verifies after it is intact.
        salvaged = 0
        for raw in port.bad_lines:
            m = _LINE_RE.match(raw[raw.rfind(b"$") :]) if b"$" in raw else None
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
        _collect_run(port, 70)
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
