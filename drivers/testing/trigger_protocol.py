"""The line protocol of docs/trigger-protocol.md, spoken with raw pyserial and no driver logic:
the contract every trigger box (the Python model in `firmware_sim`, the AVR firmware under
simavr, a box on a real port) must keep. Subclass `TriggerProtocolContract` and provide a
`port` fixture: a `RawPort` on a booted box whose `PING` has been answered.

Where two boxes disagree, docs/trigger-protocol.md decides; each rule it states is one test
here, so the suite is what "speaks protocol v1" means.
"""

from __future__ import annotations

import re
import time

import pytest
import serial
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

LINE_RE = re.compile(rb"^\$([ -~]*)\*([0-9A-F]{2})$")
#: Lead between START and pulse 0 (docs/trigger-protocol.md, "Pulses").
START_LEAD_US = 20_000


def checksum(payload: bytes) -> int:
    x = 0
    for b in payload:
        x ^= b
    return x


def host_line(payload: bytes) -> bytes:
    """A host -> box line with its `*HH` checksum, as the driver frames it."""
    return payload + b"*%02X\n" % checksum(payload)


class RawPort:
    """Minimal host side: framed lines in, checksummed lines out, no driver logic."""

    def __init__(self, path: str, baudrate: int = 115200) -> None:
        self.ser = serial.serial_for_url(path, baudrate=baudrate, timeout=0.05)
        self.buf = bytearray()
        self.bad_lines: list[bytes] = []

    def send(self, data: bytes) -> None:
        self.ser.write(data)

    def raw_line(self, timeout: float = 5.0) -> bytes:
        deadline = time.monotonic() + timeout
        while b"\n" not in self.buf:
            if time.monotonic() > deadline:
                raise TimeoutError(f"no line within {timeout} s (buffer {bytes(self.buf)!r})")
            self.buf.extend(self.ser.read(max(1, self.ser.in_waiting)))
        nl = self.buf.index(b"\n")
        line = bytes(self.buf[:nl])
        del self.buf[: nl + 1]
        return line

    def line(self, timeout: float = 5.0) -> str:
        """Next line whose checksum verifies; corrupt ones go to `bad_lines`."""
        deadline = time.monotonic() + timeout
        while True:
            raw = self.raw_line(max(0.0, deadline - time.monotonic()))
            m = LINE_RE.match(raw)
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

    def sync(self, attempts: int = 5) -> None:
        """Flush a half line out of the box and wait for its PONG (READY may have gone to a
        flushed buffer when the port was opened). A PING lost in a flood the box is still
        working through (its `ERR OVERRUN`) is sent again, as a host driver does."""
        for attempt in range(attempts):
            self.send(b"\n")
            self.send(b"PING #65535\n")
            deadline = time.monotonic() + 5.0
            try:
                while self.line(max(0.0, deadline - time.monotonic())) != "PONG #65535":
                    pass
                return
            except TimeoutError:
                if attempt == attempts - 1:
                    raise

    def close(self) -> None:
        self.ser.close()


def pulses(lines: list[str]) -> list[tuple[int, int]]:
    return [(int(f[1]), int(f[2])) for f in (ln.split() for ln in lines) if f[0] == "P"]


def collect_run(port: RawPort, n: int, timeout: float = 20.0) -> list[str]:
    """Lines up to and including `END n`."""
    out: list[str] = []
    deadline = time.monotonic() + timeout
    while True:
        line = port.line(max(0.0, deadline - time.monotonic()))
        out.append(line)
        if line == f"END {n}":
            return out


def assert_next_is_pong(port: RawPort, tag: int = 99) -> None:
    """The box answers in order: the next line after a PING is its PONG when nothing else is
    pending (a check that no line is left over, instead of watching the port for a while)."""
    port.send(f"PING #{tag}\n".encode())
    assert port.line() == f"PONG #{tag}"


def schedule(t0: int, rate_uhz: int, k: int) -> int:
    """b_k = t0 + round(k * 1e6 / rate), the exact rational with halves rounded up."""
    return t0 + (2 * k * 10**12 + rate_uhz) // (2 * rate_uhz)


BAD_LINES = [
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
    (b"RATE 1.1234567", "BADARG"),
    (b"WIDTH 0", "BADARG"),
    (b"WIDTH 1.5", "BADARG"),
    (b"WIDTH 1000001", "BADARG"),
    (b"START 0", "BADARG"),
    (b"START x", "BADARG"),
    (b"START 2147483648", "BADARG"),
    (b"TS? 0", "BADARG"),
    (b"TS? 0 0", "BADARG"),
    (b"TS? 0 65", "BADARG"),
    (b"TS? -1 2", "BADARG"),
    (b"PING #99999", "BADARG"),
    (b"PING #", "BADARG"),
    (b"START", "STATE"),
    (b"PING*00", "CHECKSUM"),
    (b"PING*G1", "CHECKSUM"),
    (b"PING*4", "CHECKSUM"),
    (b"X" * 65, "TOOLONG"),
    (b"PI\xffNG", "BADCHAR"),
    (b"PI\tNG", "BADCHAR"),
    (b"PI\x00NG", "BADCHAR"),
]


class TriggerProtocolContract:
    """What every box does on the wire; the subclass gives a `port` fixture."""

    #: The box's shortest pulse (docs: a box may refuse widths below its minimum).
    min_width_us = 1

    def test_every_command(self, port: RawPort) -> None:
        assert port.cmd("PING") == ["PONG"]
        ident = port.cmd("ID?")[0].split()
        assert ident[0] == "ID"
        assert len(ident) == 5
        assert port.cmd("rate 500") == ["OK RATE 500.000000"]  # commands are case-insensitive
        assert port.cmd("WIDTH 100") == ["OK WIDTH 100"]
        assert port.cmd("STATUS?") == ["STATUS IDLE count=0 target=0 rate=500.000000 width=100 t0=-1"]
        assert port.cmd("ARM") == ["OK ARM"]
        assert port.cmd("STATUS?")[0].startswith("STATUS ARMED count=0 target=0")
        assert port.cmd("COUNT?") == ["COUNT 0"]
        clock = int(port.cmd("CLOCK?")[0].split()[1])
        reply = port.cmd("START 5")[0].split()
        assert reply[:2] == ["OK", "START"]
        assert reply[3] == "5"
        t0 = int(reply[2])
        assert clock + START_LEAD_US <= t0 <= clock + START_LEAD_US + 1_000_000
        run = collect_run(port, 5)
        assert pulses(run) == [(k, t0 + 2000 * k) for k in range(5)]
        assert port.cmd("COUNT?") == ["COUNT 5"]
        assert port.cmd("STATUS?") == [f"STATUS IDLE count=5 target=5 rate=500.000000 width=100 t0={t0}"]
        assert port.cmd("TS? 1 3") == [f"T {k} {t0 + 2000 * k}" for k in (1, 2, 3)] + ["OK TS 3"]
        assert port.cmd("TS? 3 10") == [f"T {k} {t0 + 2000 * k}" for k in (3, 4)] + ["OK TS 2"]
        assert port.cmd("TS? 9 1") == ["OK TS 0"]
        assert port.cmd("TS? 9999999999 1") == ["OK TS 0"]
        assert port.cmd("STOP") == ["OK STOP 5"]
        later = int(port.cmd("CLOCK?")[0].split()[1])
        assert later >= t0 + 4 * 2000  # the clock runs on, never reset
        # A checksummed command line is accepted; '$' in front is optional; CR LF is a newline.
        payload = b"PING #9"
        port.send(b"$" + payload + b"*%02X\r\n" % checksum(payload))
        assert port.line() == "PONG #9"
        port.send(payload + b"*%02x\n" % checksum(payload))  # lower-case hex too
        assert port.line() == "PONG #9"

    @pytest.mark.parametrize(("line", "code"), BAD_LINES)
    def test_bad_lines_get_err(self, port: RawPort, line: bytes, code: str) -> None:
        port.send(line + b"\n")
        reply = port.line().split()
        assert reply[:2] == ["ERR", code], reply
        assert port.cmd("PING") == ["PONG"]  # and the box keeps working

    def test_err_echoes_the_tag_and_keeps_framing_bytes_out(self, port: RawPort) -> None:
        reply = port.cmd("RATE fa$t", tag=42)[0]
        assert reply == "ERR BADARG rate 'fa?t' not a decimal in 0.001..10000 Hz"
        assert port.cmd("NOPE", tag=0) == ["ERR UNKNOWN unknown command 'NOPE'"]
        # '*' reaches a command only inside a checksummed line; the box shows it as '?' too.
        payload = b"F$O*O #5"
        port.send(payload + b"*%02X\n" % checksum(payload))
        assert port.line() == "ERR UNKNOWN unknown command 'F?O?O' #5"
        port.send(b"PING*$4\n")
        assert port.line() == "ERR CHECKSUM checksum *?4 does not match the line"

    def test_wrong_state(self, port: RawPort) -> None:
        port.cmd("RATE 1000")
        port.cmd("WIDTH 100")
        assert port.cmd("START 5")[0].startswith("ERR STATE START needs ARMED, box is IDLE")
        port.cmd("ARM")
        assert port.cmd("START")[0].startswith("OK START")
        for cmd in ("RATE 10", "WIDTH 50", "ARM", "START", "START 3"):
            assert port.cmd(cmd)[0].startswith("ERR STATE"), cmd
        assert port.cmd("PING") == ["PONG"]
        assert port.cmd("STOP")[0].startswith("OK STOP")
        assert port.cmd("STOP")[0].startswith("OK STOP")  # STOP is allowed in every state
        assert port.cmd("START")[0].startswith("ERR STATE")  # needs a new ARM

    def test_width_must_be_shorter_than_period(self, port: RawPort) -> None:
        port.cmd("RATE 1000")
        port.cmd("WIDTH 1000")
        port.cmd("ARM")
        assert port.cmd("START 3")[0] == "ERR BADARG width 1000 us >= period 1000.0 us"
        port.cmd("WIDTH 1500")
        port.cmd("RATE 700")
        assert port.cmd("START 3")[0] == "ERR BADARG width 1500 us >= period 1428.6 us"
        assert port.cmd("STATUS?")[0].startswith("STATUS ARMED")  # still armed, nothing ran

    def test_widths_below_the_box_minimum_are_refused(self, port: RawPort) -> None:
        assert port.cmd(f"WIDTH {self.min_width_us}") == [f"OK WIDTH {self.min_width_us}"]
        if self.min_width_us > 1:
            reply = port.cmd(f"WIDTH {self.min_width_us - 1}")[0]
            assert reply.startswith("ERR BADARG width")

    # One contract method runs on several box classes: each has its own port (differing_executors).
    @settings(
        max_examples=40,
        deadline=None,
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.differing_executors],
    )
    # Garbage, not a command: a leading word of capitals could be a real one (b"PING #0" was
    # drawn once and answered PONG, rightly); the named bad lines above cover those.
    @given(
        garbage=st.binary(min_size=1, max_size=200).filter(
            lambda b: b"\n" not in b and re.match(rb"[A-Z?]+([ #*\r]|$)", b) is None
        )
    )
    def test_random_garbage_gets_err_and_box_survives(self, port: RawPort, garbage: bytes) -> None:
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

    def test_overlong_line_one_err_even_in_pieces(self, port: RawPort) -> None:
        port.send(b"A" * 100)
        # Real time on purpose: a pause on the link, so the line reaches the box in pieces.
        time.sleep(0.02)
        port.send(b"B" * 3000 + b"\n")
        assert port.line() == "ERR TOOLONG line exceeds 64 bytes"
        assert_next_is_pong(port)  # no second ERR: the box answers in order, so it would come first
        port.send(b"P" * 64 + b"\n")  # exactly at the limit: parsed, unknown
        assert port.line().startswith("ERR UNKNOWN")
        port.send(b"P" * 64 + b"\r\n")  # the limit, and a CR that is not part of the line
        assert port.line().startswith("ERR UNKNOWN")

    @pytest.mark.parametrize(("rate", "n"), [("700", 60), ("3200", 9), ("29.97", 4), ("0.5", 2)])
    def test_pulse_schedule_is_the_documented_integer_formula(self, port: RawPort, rate: str, n: int) -> None:
        """b_k = t0 + round(k * 1e6 / rate), halves up (3200 Hz: 312.5 us, 0.5 Hz: 2 s)."""
        rate_uhz = round(float(rate) * 1e6)
        port.cmd(f"RATE {rate}")
        port.cmd("WIDTH 100")
        port.cmd("ARM")
        t0 = int(port.cmd(f"START {n}")[0].split()[2])
        run = collect_run(port, n, timeout=30.0)
        assert pulses(run) == [(k, schedule(t0, rate_uhz, k)) for k in range(n)]
        assert port.cmd("STATUS?")[0].startswith(f"STATUS IDLE count={n} target={n}")
        assert_next_is_pong(port)  # nothing after END: the run is over
        got = port.cmd(f"TS? 0 {n}")
        assert got[:-1] == [f"T {k} {schedule(t0, rate_uhz, k)}" for k in range(n)]

    def test_start_then_stop(self, port: RawPort) -> None:
        port.cmd("RATE 1000")
        port.cmd("WIDTH 100")
        port.cmd("ARM")
        port.cmd("START")
        lines: list[str] = []
        while len(pulses(lines)) <= 30:  # wait for 31 pulses, not for a fixed time
            lines.append(port.line())
        port.send(b"STOP #3\n")
        while not (line := port.line()).endswith("#3"):
            lines.append(line)
        count = int(line.split()[2])
        assert count > 30
        assert [k for k, _ in pulses(lines)] == list(range(count))  # every pulse before OK STOP
        assert_next_is_pong(port)  # the box is stopped: nothing after OK STOP
        assert port.cmd("STATUS?")[0].startswith(f"STATUS IDLE count={count} target=0")

    def test_arm_forgets_the_last_run(self, port: RawPort) -> None:
        port.cmd("RATE 2000")
        port.cmd("WIDTH 100")
        port.cmd("ARM")
        t0 = int(port.cmd("START 70")[0].split()[2])
        collect_run(port, 70)
        got = port.cmd("TS? 0 64")
        assert got[-1] == "OK TS 64"
        assert got[:-1] == [f"T {k} {t0 + 500 * k}" for k in range(64)]
        port.cmd("ARM")
        assert port.cmd("TS? 0 1") == ["OK TS 0"]
        assert port.cmd("STATUS?")[0] == "STATUS ARMED count=0 target=0 rate=2000.000000 width=100 t0=-1"

    def test_diag_counts(self, port: RawPort) -> None:
        fields = port.cmd("DIAG?")[0].split()
        assert fields[0] == "DIAG"
        keys = {f.split("=")[0] for f in fields[1:]}
        assert keys >= {"records_dropped", "rx_lost", "late_edges"}
        assert all(f.split("=")[1].isdigit() for f in fields[1:])
