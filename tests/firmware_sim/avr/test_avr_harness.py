"""The simavr harness with its test firmware: the pty line, UART echo over the pty at the line
rate, Timer1 compare edges by AVR cycle, the control protocol (RUN / FREE / SET / NOP), a
firmware that stops, and shutdown. Rates are checked in AVR cycles, never in wall time."""

from __future__ import annotations

import itertools
import re
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial

import firmware_sim.avr.harness as harness_module
from firmware_sim.avr import AvrHarness, Edge, Step, find_binary, parse_edge_line
from rigd.core.errors import BackendUnavailableError, DeviceError, ProtocolError

#: simavr's UART frame at UBRR=1, U2X (16 cycles a bit): start + 8 data + parity + stop = 11
#: bits; simavr 1.6 counts a parity bit whether or not parity is on.
CYCLES_PER_BYTE = 176
#: OC1A toggles every 1000 Timer1 ticks at clk/8.
EDGE_PERIOD = 8000
PTY_LINE = re.compile(r"^pty: /dev/pts/\d+$")
#: Every byte but the firmware's commands 'S' (start pulses) and 'Q' (stop them).
PLAIN_BYTES = bytes(b for b in range(256) if b not in b"SQ")


@pytest.fixture
def control(echo_elf: Path, tmp_path: Path) -> Iterator[AvrHarness]:
    h = AvrHarness(
        echo_elf,
        clock="control",
        pins={"TRIG": "B1", "LED": "B5"},
        input_pins={"EXT": "D2"},
        edges_path=tmp_path / "edges.txt",
    )
    yield h
    h.close()


def open_port(h: AvrHarness) -> serial.Serial:
    return serial.Serial(h.port_path, baudrate=1_000_000, timeout=10)


def free_in_thread(h: AvrHarness) -> tuple[threading.Thread, list[Step]]:
    out: list[Step] = []
    thread = threading.Thread(target=lambda: out.append(h.free()), daemon=True)
    thread.start()
    return thread, out


def interrupt_until_done(h: AvrHarness, thread: threading.Thread) -> None:
    """NOP until the FREE returns: a NOP that overtakes the FREE is answered and skipped."""
    deadline = time.monotonic() + 20
    while thread.is_alive():
        assert time.monotonic() < deadline, "FREE did not return after NOP"
        h.interrupt()
        thread.join(0.1)


def start_pulses(h: AvrHarness, port: serial.Serial) -> Step:
    """Send 'S' (the firmware enables its compare interrupt): FREE returns `scheduled` as soon
    as the RX ISR sets OCIE1A, before its echo is sent (that needs more AVR time)."""
    port.write(b"S")
    step = h.free()
    assert not step.quiet
    return step


def test_first_stdout_line_is_the_pty(echo_elf: Path) -> None:
    proc = subprocess.Popen(
        [str(find_binary()), "--elf", str(echo_elf), "--clock", "control"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    first = proc.stdout.readline().rstrip("\n")
    out, err = proc.communicate("QUIT\n", timeout=10)
    assert PTY_LINE.match(first), first
    assert proc.returncode == 0, err
    assert out == ""


def test_protocol_lines_and_order(echo_elf: Path) -> None:
    """Exact line formats; every EDGE before the AT that covers its cycle."""
    proc = subprocess.Popen(
        [
            str(find_binary()),
            "--elf",
            str(echo_elf),
            "--clock",
            "control",
            "--pin",
            "TRIG=B1",
            "--quiet-reg",
            "0x6F:0x06",
            "--input-pin",
            "EXT=D2",
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        bufsize=1,
    )
    assert proc.stdin is not None
    assert proc.stdout is not None
    port = proc.stdout.readline().split()[1]

    def ask(line: str) -> list[str]:
        assert proc.stdin is not None
        assert proc.stdout is not None
        proc.stdin.write(line + "\n")
        proc.stdin.flush()
        lines = []
        while True:
            got = proc.stdout.readline().rstrip("\n")
            lines.append(got)
            if not got.startswith("EDGE "):
                return lines

    try:
        assert ask("RUN 10000") == ["AT 10000 quiet"]
        with serial.Serial(port, baudrate=1_000_000, timeout=10) as ser:
            ser.write(b"S")
            (at,) = ask("FREE")
            assert re.fullmatch(r"AT \d+ scheduled", at), at
            lines = ask("RUN 60000")
        *edges, at = lines
        m = re.fullmatch(r"AT (\d+) scheduled", at)
        assert m, at
        assert 60000 <= int(m.group(1)) < 60000 + 5
        assert len(edges) == 6
        for edge in edges:
            e = re.fullmatch(r"EDGE (\d+) TRIG ([01])", edge)
            assert e, edge
            assert int(e.group(1)) <= int(m.group(1))
        assert ask("SET 5 EXT 1") == ["ERR SET: cycle 5 is in the past (now " + m.group(1) + ")"]
        assert ask("SET 70000 EXT 1") == ["OK"]
        assert ask("NOP") == ["NOP"]
        assert ask("HELLO")[0].startswith("ERR unknown command: HELLO")
        assert ask("RUN 5") == [at]  # already past: answers where it is
    finally:
        _out, err = proc.communicate("QUIT\n", timeout=10)
    assert proc.returncode == 0, err


def test_edges_are_8000_cycles_apart(control: AvrHarness, tmp_path: Path) -> None:
    with open_port(control) as port:
        start = start_pulses(control, port)
        step = control.run_until(start.cycle + 20 * EDGE_PERIOD + 100)
        assert port.read(1) == b"S"
    edges = start.edges + step.edges
    assert len(edges) == 20
    assert all(e.pin == "TRIG" for e in edges)
    assert [e.value for e in edges] == [1, 0] * 10
    # The firmware sleeps when each compare fires: simavr's sleep jump lands on the compare
    # cycle + 1 every time, so the period is exact (no instruction jitter).
    assert {b.cycle - a.cycle for a, b in itertools.pairwise(edges)} == {EDGE_PERIOD}
    # the first compare is 1000 ticks after the 'S' handler set OCR1A = TCNT1 + 1000
    assert start.cycle < edges[0].cycle <= start.cycle + EDGE_PERIOD + 16
    control.close()
    written = [parse_edge_line(line) for line in (tmp_path / "edges.txt").read_text().splitlines()]
    assert written == edges


def test_free_stands_still_while_quiet_and_returns_on_schedule(control: AvrHarness) -> None:
    assert control.run_until(50_000) == Step(50_000, True, [])
    thread, out = free_in_thread(control)
    interrupt_until_done(control, thread)
    assert out == [Step(50_000, True, [])]  # quiet and asleep: not one cycle passed

    with open_port(control) as port:
        thread, out = free_in_thread(control)
        port.write(b"S")  # arrives while time stands still: received from cycle 50000 on
        thread.join(20)
        assert not thread.is_alive()
        control.run_until(60_000)
        assert port.read(1) == b"S"
    (step,) = out
    assert not step.quiet
    # the byte takes one frame to arrive, then the RX ISR sets OCIE1A
    assert 50_000 + CYCLES_PER_BYTE <= step.cycle < 50_000 + CYCLES_PER_BYTE + 100


def test_echo_runs_at_the_uart_line_rate(control: AvrHarness) -> None:
    """50 bytes in and echoed back cost ~53 frames of AVR time: FREE serves them and stands
    still again once the UART is idle, so the cycles spent are the UART's alone. The echo of
    the last byte trails its reception by ~2.6 frames (seen: 9265 cycles for 50 bytes):
    simavr 1.6 keeps two bytes in flight on TX (UDR + shift register) and re-raises UDRE a
    frame after each write."""
    start = control.run_until(20_000)
    payload = PLAIN_BYTES[:50]
    with open_port(control) as port:
        thread, out = free_in_thread(control)
        port.write(payload)
        assert port.read(len(payload)) == payload
        interrupt_until_done(control, thread)
    (step,) = out
    assert step.quiet
    spent = step.cycle - start.cycle
    assert len(payload) * CYCLES_PER_BYTE <= spent <= (len(payload) + 4) * CYCLES_PER_BYTE, spent


def test_set_drives_an_input_pin_at_its_cycle(control: AvrHarness) -> None:
    control.run_until(100_000)
    control.set_pin(150_000, "EXT", 1)
    control.set_pin(160_000, "EXT", 0)
    step = control.run_until(200_000)
    # INT0 mirrors PD2 onto PB5: the ISR writes PORTB a few dozen cycles after the SET
    assert [(e.pin, e.value) for e in step.edges] == [("LED", 1), ("LED", 0)]
    assert 150_000 < step.edges[0].cycle < 150_100
    assert 160_000 < step.edges[1].cycle < 160_100
    with pytest.raises(ProtocolError, match="in the past"):
        control.set_pin(10, "EXT", 1)
    with pytest.raises(ProtocolError, match="not an --input-pin"):
        control.set_pin(300_000, "NOPE", 1)


def test_a_stopped_firmware_is_a_clean_error(harness_env: Path) -> None:
    elf = harness_env / "testfw_sleep_cli.elf"
    h = AvrHarness(elf, clock="control", pins={"LED": "B5"})
    with pytest.raises(DeviceError, match=r"stopped \(sleeping with interrupts off\) at cycle \d+, PC 0x"):
        h.run_until(10_000)
    h.close()  # already reported: no second error
    assert h.returncode == 2

    run = subprocess.run(
        [str(find_binary()), "--elf", str(elf), "--clock", "max"], capture_output=True, text=True, timeout=30
    )
    assert run.returncode == 2
    assert PTY_LINE.match(run.stdout.splitlines()[0])
    (line,) = run.stderr.splitlines()
    assert re.fullmatch(
        r"avr_harness: the AVR stopped \(sleeping with interrupts off\) at cycle \d+, PC 0x[0-9a-f]+ "
        r"\(byte address\)",
        line,
    ), line


def test_real_clock_echoes_over_pyserial_and_close_cleans_up(echo_elf: Path, tmp_path: Path) -> None:
    edges_path = tmp_path / "edges.txt"
    h = AvrHarness(echo_elf, edges_path=edges_path)  # real clock, the 328P's TRIG and LED
    try:
        payload = PLAIN_BYTES * 4
        with open_port(h) as port:
            port.write(payload)
            assert port.read(len(payload)) == payload
            port.write(b"S")
            assert port.read(1) == b"S"
            deadline = time.monotonic() + 20
            while len(edges_path.read_text().splitlines()) < 6:  # flushed every 100 ms
                assert time.monotonic() < deadline, "no edges written"
                time.sleep(0.05)
    finally:
        h.close()
    assert h.returncode == 0
    h.close()  # idempotent
    edges = [parse_edge_line(line) for line in edges_path.read_text().splitlines()]
    assert {e.pin for e in edges} == {"TRIG"}
    assert {b.cycle - a.cycle for a, b in itertools.pairwise(edges)} == {EDGE_PERIOD}


def test_missing_binary_says_how_to_build_it(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv(harness_module.BINARY_ENV, str(tmp_path / "nope"))
    with pytest.raises(BackendUnavailableError, match="RIGD_AVR_HARNESS"):
        find_binary()
    monkeypatch.delenv(harness_module.BINARY_ENV)
    monkeypatch.setattr(harness_module, "DEFAULT_BINARY", tmp_path / "avr_harness")
    with pytest.raises(BackendUnavailableError, match=r"make -C .*firmware/avr_harness"):
        AvrHarness(tmp_path / "fw.elf")


def test_edge_lines_parse_strictly() -> None:
    assert parse_edge_line("123 TRIG 1") == Edge(123, "TRIG", 1)
    for bad in ("123 TRIG", "x TRIG 1", "1 TRIG 2", "1 TRIG 1 extra"):
        with pytest.raises(ProtocolError):
            parse_edge_line(bad)


def pty_queue(port: serial.Serial) -> int:
    """Bytes waiting in the pty for the host to read."""
    return port.in_waiting


@pytest.mark.slow
def test_max_clock_stalls_instead_of_losing_output(echo_elf: Path) -> None:
    """Echo 300 kB while nobody reads the pty, with a 4 KiB harness output buffer: far more
    than it and the pty's queues hold, so the harness must stall the AVR (and so the host's
    writes) rather than drop a byte. Reading starts once the pty's queue stops growing (it is
    full); every byte comes back, in order."""
    payload = PLAIN_BYTES * (300_000 // len(PLAIN_BYTES))
    with AvrHarness(echo_elf, clock="max", out_buffer=4096) as h, open_port(h) as port:
        port.write_timeout = 120
        writer = threading.Thread(target=port.write, args=(payload,), daemon=True)
        writer.start()
        deadline = time.monotonic() + 60
        queued = -1
        while pty_queue(port) != queued:
            assert time.monotonic() < deadline, "the pty's queue kept growing"
            queued = pty_queue(port)
            writer.join(0.3)
        assert writer.is_alive(), "all 300 kB fit somewhere: the stall was not exercised"
        port.timeout = 120
        echoed = port.read(len(payload))
        writer.join(120)
        assert not writer.is_alive()
    assert len(echoed) == len(payload)
    assert echoed == payload


@pytest.mark.slow
def test_real_clock_counts_the_output_it_loses(echo_elf: Path) -> None:
    """Real time cannot stall: with nobody reading the pty and a 16-byte output buffer, echoed
    bytes are lost, and the harness says how many on stderr."""
    payload = PLAIN_BYTES * (300_000 // len(PLAIN_BYTES))  # ~3.3 s at 1 Mbaud
    h = AvrHarness(echo_elf, out_buffer=16)
    try:
        with open_port(h) as port:
            port.write_timeout = 60
            port.write(payload)
            port.flush()
            queued = port.in_waiting  # (the pty hangs up once the harness has exited)
            h.close()
    finally:
        h.close()
    assert h.returncode == 0
    lost = re.search(r"avr_harness: (\d+) firmware bytes lost", h.stderr_tail())
    assert lost, h.stderr_tail()
    assert int(lost.group(1)) > 0
    assert queued + int(lost.group(1)) <= len(payload)


def test_close_ends_a_blocked_free(control: AvrHarness) -> None:
    control.run_until(30_000)
    thread, out = free_in_thread(control)
    control.close()  # QUIT: the FREE answers `AT 30000 quiet`, then the harness exits
    thread.join(20)
    assert not thread.is_alive()
    assert out in ([Step(30_000, True, [])], [])  # [] if QUIT overtook the FREE
    assert control.returncode == 0


def test_a_file_that_is_no_firmware_is_refused_before_the_pty(harness_env: Path, tmp_path: Path) -> None:
    not_elf = tmp_path / "fw.elf"
    not_elf.write_text("not an ELF\n")
    with pytest.raises(DeviceError, match=r"--elf .*fw\.elf: (not an AVR ELF|no program in it)"):
        AvrHarness(not_elf, clock="control")
    with pytest.raises(DeviceError, match=r"the atmega328p has no port L"):
        AvrHarness(harness_env / "testfw_busy.elf", pins={"X": "L1"})


def test_atmega2560_with_the_default_pins(harness_env: Path) -> None:
    """The Mega's defaults: TRIG=B5 (OC1A), LED=B7, quiet while TIMSK1 & 0x06 == 0."""
    elf = harness_env / "testfw_echo_timer_2560.elf"
    with AvrHarness(elf, mcu="atmega2560", clock="control", input_pins={"EXT": "D0"}) as h:
        with open_port(h) as port:
            start = start_pulses(h, port)
            step = h.run_until(start.cycle + 6 * EDGE_PERIOD + 100)
            assert port.read(1) == b"S"
        edges = start.edges + step.edges
        assert [(e.pin, e.value) for e in edges] == [("TRIG", 1), ("TRIG", 0)] * 3
        assert {b.cycle - a.cycle for a, b in itertools.pairwise(edges)} == {EDGE_PERIOD}
        h.set_pin(step.cycle + 1000, "EXT", 1)
        (led,) = h.run_until(step.cycle + 2000).edges
        assert led.pin == "LED"
        assert led.value == 1
