"""`python -m firmware_sim.avr`: the pty line first, edges to the file, a clean stop on
SIGTERM, and a non-zero exit when the firmware stops on its own."""

from __future__ import annotations

import itertools
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import serial

from firmware_sim.avr import parse_edge_line
from firmware_sim.avr.harness import REPO_ROOT


def start_cli(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "firmware_sim.avr", *args],
        cwd=REPO_ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_cli_serves_the_pty_and_writes_edges(echo_elf: Path, tmp_path: Path) -> None:
    edges_path = tmp_path / "edges.txt"
    proc = start_cli("--elf", str(echo_elf), "--edges", str(edges_path))
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline().rstrip("\n")
        assert re.fullmatch(r"pty: /dev/pts/\d+", first), first
        with serial.Serial(first.removeprefix("pty: "), baudrate=1_000_000, timeout=10) as port:
            port.write(b"hello S")
            assert port.read(7) == b"hello S"
        deadline = time.monotonic() + 20
        while not edges_path.exists() or len(edges_path.read_text().splitlines()) < 4:
            assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
            assert time.monotonic() < deadline, "no edges written"
            time.sleep(0.05)
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    assert out == ""  # nothing after the pty line
    edges = [parse_edge_line(line) for line in edges_path.read_text().splitlines()]
    assert {e.pin for e in edges} == {"TRIG"}
    assert {b.cycle - a.cycle for a, b in itertools.pairwise(edges)} == {8000}


def test_cli_fails_when_the_firmware_stops(harness_env: Path) -> None:
    proc = start_cli("--elf", str(harness_env / "testfw_sleep_cli.elf"), "--clock", "max")
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 1
    assert re.match(r"pty: /dev/pts/\d+\n", out)
    assert "the AVR stopped (sleeping with interrupts off)" in err
