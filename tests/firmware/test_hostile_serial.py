"""Hostile serial input against the firmware while it pulses: every bad line gets its
documented ERR, the edges keep their ticks, no pulse record is lost (TS? brings back what the
saturated line could not carry) and the box never resets."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from drivers.testing.trigger_protocol import RawPort, host_line, schedule
from firmware_sim.testing.avr_box import CYCLES_PER_US, FirmwareProcess

ERR_CODES = {"UNKNOWN", "BADARG", "STATE", "TOOLONG", "BADCHAR", "CHECKSUM", "OVERRUN"}
HOSTILE = [
    b"X" * 300,  # overlong
    b"PI\xffNG #1",  # non-ASCII
    "R\u00c4TE 10".encode(),  # UTF-8
    b"PING*00",  # bad checksum
    b"\x00\x01\x02garbage\x7f",  # control bytes
    b"$$$***",  # framing bytes
    b"RATE 1e3 #2",  # bad number
    b"START #3",  # wrong state while running
    b"WIDTH 5 #4",  # below the minimum, and RUNNING
    b"TS? 0 999 #5",
]


def _flood(n: int) -> bytes:
    """Hostile lines between valid checksummed PINGs, garbage between lines."""
    parts = []
    for i in range(n):
        parts.append(host_line(b"PING #%d" % (i % 60000)))
        parts.append(HOSTILE[i % len(HOSTILE)] + b"\n")
        if i % 7 == 0:
            parts.append(b"\x80\x81 noise \r\r")  # glued onto the next line: one BADCHAR
    return b"".join(parts)


@pytest.mark.slow
def test_a_flood_of_hostile_lines_during_a_1khz_run(serve: type[FirmwareProcess]) -> None:
    box = serve("atmega328p")
    port = RawPort(box.port, baudrate=1_000_000)
    try:
        port.sync()
        port.cmd("RATE 1000")
        port.cmd("WIDTH 100")
        port.cmd("ARM")
        n_pulses = 3000
        t0 = int(port.cmd(f"START {n_pulses}")[0].split()[2])
        flood = _flood(6000)  # ~170 kB: nearly two seconds of a 1 Mbaud line, at full rate
        writer = threading.Thread(target=port.send, args=(flood,))
        writer.start()
        lines: list[str] = []
        while f"END {n_pulses}" not in lines:
            lines.append(port.line(timeout=60.0))
        writer.join(60)
        # Everything the flood left in the box's buffers is answered before this PONG; a PING
        # lost to the flood's overrun is sent again.
        while "PONG #60001" not in lines:
            port.send(b"PING #60001\n")
            try:
                while (line := port.line(timeout=5.0)) != "PONG #60001":
                    lines.append(line)
                lines.append(line)
            except TimeoutError:
                continue
        kinds = {ln.split()[0] for ln in lines}
        assert kinds <= {"P", "END", "PONG", "ERR"}, kinds - {"P", "END", "PONG", "ERR"}
        codes = {ln.split()[1] for ln in lines if ln.startswith("ERR ")}
        assert codes <= ERR_CODES
        assert {"TOOLONG", "BADCHAR", "CHECKSUM", "BADARG", "STATE"} <= codes
        assert port.bad_lines == []  # every line the box sent is framed and checksummed
        # No record lost: what the saturated line could not carry comes back by TS?.
        got = {int(f[1]): int(f[2]) for f in (ln.split() for ln in lines) if f[0] == "P"}
        for first in range(0, n_pulses, 64):
            if all(k in got for k in range(first, min(first + 64, n_pulses))):
                continue
            for t_line in port.cmd(f"TS? {first} 64")[:-1]:
                _, k, b = t_line.split()
                assert got.setdefault(int(k), int(b)) == int(b)
        assert sorted(got) == list(range(n_pulses))
        assert [got[k] for k in range(n_pulses)] == [schedule(t0, 1_000_000_000, k) for k in range(n_pulses)]
        diag = dict(f.split("=") for f in port.cmd("DIAG?")[0].split()[1:])
        assert diag["late_edges"] == "0"
        # Never reset: no READY, and the clock runs on from before the run.
        assert port.cmd("STATUS?")[0].startswith(f"STATUS IDLE count={n_pulses} target={n_pulses}")
        assert int(port.cmd("CLOCK?")[0].split()[1]) > got[n_pulses - 1]
        # No pulse late by more than one tick.
        changes = box.wait_for_changes(2 * n_pulses + 1)
        rises = np.array([c.cycle for c in changes if c.value == 1], dtype=np.int64)
        assert len(rises) == n_pulses
        late = rises - np.array([got[k] for k in range(n_pulses)]) * CYCLES_PER_US
        assert late.min() >= 0, late.min()
        assert late.max() < 8, late.max()
    finally:
        port.close()
