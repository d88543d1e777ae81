"""The trigger-box firmware under simavr as a process, for tests and benches: build the
images and the harness with `make`, serve an image on a pty with `python -m firmware_sim.avr`,
read back its pin edges."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[2]
FIRMWARE_DIR = REPO / "firmware" / "trigger_box"
HARNESS_DIR = REPO / "firmware" / "avr_harness"
CYCLES_PER_US = 16


def _make(directory: Path) -> Path:
    subprocess.run(["make", "-s", "-C", str(directory)], check=True, capture_output=True, text=True)
    return directory / "build"


def build_firmware() -> Path:
    """`make -C firmware/trigger_box`; its build folder."""
    return _make(FIRMWARE_DIR)


def build_harness() -> Path:
    """`make -C firmware/avr_harness`; the harness binary."""
    return _make(HARNESS_DIR) / "avr_harness"


@dataclass(frozen=True, slots=True)
class PinChange:
    cycle: int
    pin: str
    value: int


class FirmwareProcess:
    """`python -m firmware_sim.avr --elf ELF --edges FILE` until `close()`."""

    def __init__(
        self, elf: Path, *, mcu: str, clock: str = "real", edges: Path, pins: list[str] | None = None
    ) -> None:
        self.elf = elf
        self.edges_path = edges
        cmd = [sys.executable, "-m", "firmware_sim.avr", "--elf", str(elf), "--mcu", mcu]
        cmd += ["--edges", str(edges), "--clock", clock]
        for pin in pins or []:
            cmd += ["--pin", pin]
        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=dict(os.environ)
        )
        assert self.proc.stdout is not None
        first = self.proc.stdout.readline().strip()
        if not first.startswith("pty: "):
            err = self.proc.stderr.read() if self.proc.stderr else ""
            self.proc.kill()
            raise RuntimeError(f"{' '.join(cmd)}: first line {first!r}, not 'pty: ...'\n{err}")
        self.port = first.removeprefix("pty: ")

    def pin_changes(self, pin: str = "TRIG") -> list[PinChange]:
        """The edges file so far (the harness flushes it at least every 100 ms and at exit)."""
        out = []
        text = self.edges_path.read_text()
        complete = text[: text.rfind("\n") + 1]  # the harness may be writing the last line
        for line in complete.splitlines():
            cycle, name, value = line.split()
            if name == pin:
                out.append(PinChange(int(cycle), name, int(value)))
        return out

    def wait_for_changes(self, n: int, pin: str = "TRIG", timeout_s: float = 30.0) -> list[PinChange]:
        """Poll the edges file until it holds `n` changes of `pin` (a state, not a delay)."""
        deadline = time.monotonic() + timeout_s
        while True:
            got = self.pin_changes(pin) if self.edges_path.exists() else []
            if len(got) >= n or time.monotonic() > deadline:
                return got
            time.sleep(0.05)

    def close(self) -> str:
        """Stop the process (SIGTERM, then SIGKILL); its stderr."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        err = self.proc.stderr.read() if self.proc.stderr else ""
        for stream in (self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()
        return err
