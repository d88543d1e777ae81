"""Drive `avr_harness` (firmware/avr_harness/): real AVR firmware under simavr, its UART0 on a
pseudo-terminal the rig opens like the trigger box's serial port, its pins watched for edges.

The harness is a C program (simavr is a C library); this module finds it, spawns it, reads its
`pty:` line and, in `control` clock mode, speaks its line protocol (RUN / FREE / SET / NOP /
QUIT on stdin; EDGE / AT / OK / NOP / ERR on stdout), so tests can step the firmware cycle by
cycle instead of racing the wall clock.
"""

from __future__ import annotations

import logging
import os
import select
import subprocess
import threading
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Literal, NamedTuple

from rigd.core.errors import BackendUnavailableError, DeviceError, DeviceTimeoutError, ProtocolError

log = logging.getLogger(__name__)

#: The repository checkout this package sits in.
REPO_ROOT = Path(__file__).resolve().parents[2]
HARNESS_DIR = REPO_ROOT / "firmware" / "avr_harness"
DEFAULT_BINARY = HARNESS_DIR / "build" / "avr_harness"
BUILD_COMMAND = f"make -C {HARNESS_DIR}"
#: Environment variable naming another harness binary (a CI build elsewhere).
BINARY_ENV = "RIGD_AVR_HARNESS"
#: stderr lines kept for error messages.
STDERR_TAIL_LINES = 40

ClockMode = Literal["real", "max", "control"]
QUIET_WORDS = ("quiet", "scheduled")


@dataclass(frozen=True, slots=True)
class McuDefaults:
    """Per-MCU wiring of the trigger box: watched pins (name -> PORTBIT) and the register whose
    masked bits are all zero while no pulse is scheduled (the timer-compare interrupt enables)."""

    pins: Mapping[str, str]
    quiet_reg: tuple[int, int]


#: TIMSK1 is data address 0x6F on both; OCIE1A|OCIE1B = 0x06 (the 2560's OCIE1C, bit 3, is left
#: out: the trigger firmware schedules its pulses on compare A and B only).
MCU_DEFAULTS: dict[str, McuDefaults] = {
    "atmega328p": McuDefaults(pins={"TRIG": "B1", "LED": "B5"}, quiet_reg=(0x6F, 0x06)),
    "atmega2560": McuDefaults(pins={"TRIG": "B5", "LED": "B7"}, quiet_reg=(0x6F, 0x06)),
}


@dataclass(frozen=True, slots=True)
class Edge:
    """A watched pin changed to `value` at AVR cycle `cycle`."""

    cycle: int
    pin: str
    value: int


class Step(NamedTuple):
    """Where a RUN or FREE stopped: the AVR cycle, whether the firmware was quiet (nothing
    scheduled), the edges since the previous answer, and whether bytes from the host were
    waiting for the firmware then."""

    cycle: int
    quiet: bool
    edges: list[Edge]
    host_waiting: bool = False


def find_binary() -> Path:
    """The harness binary: $RIGD_AVR_HARNESS, else the checkout's build output."""
    env = os.environ.get(BINARY_ENV)
    if env:
        path = Path(env)
        if not path.is_file():
            raise BackendUnavailableError(f"{BINARY_ENV}={env}: no such file (the simavr harness binary)")
        return path
    if not DEFAULT_BINARY.is_file():
        raise BackendUnavailableError(
            f"the simavr harness {DEFAULT_BINARY} is not built: run `{BUILD_COMMAND}` "
            "(needs gcc, libsimavr-dev, libelf-dev; gcc-avr and avr-libc for its test firmware)"
        )
    return DEFAULT_BINARY


def parse_edge_line(line: str) -> Edge:
    """`<cycle> <pin> <0|1>` (the edges file) -> Edge; anything else is a ProtocolError."""
    parts = line.split()
    if len(parts) != 3 or not parts[0].isdigit() or parts[2] not in ("0", "1"):
        raise ProtocolError(f"not an edge line (want '<cycle> <pin> <0|1>'): {line!r}")
    return Edge(int(parts[0]), parts[1], int(parts[2]))


class AvrHarness:
    """One `avr_harness` process serving one firmware ELF on a pty.

    `real` and `max` clocks run on their own until close(); `control` waits for run_until(),
    free() and set_pin(). close() ends the process in every mode (idempotent).
    """

    def __init__(
        self,
        elf: Path,
        *,
        mcu: str = "atmega328p",
        freq_hz: int = 16_000_000,
        clock: ClockMode = "real",
        pins: Mapping[str, str] | None = None,
        input_pins: Mapping[str, str] | None = None,
        edges_path: Path | None = None,
        quiet_reg: tuple[int, int] | Literal["default"] | None = "default",
        binary: Path | None = None,
        out_buffer: int | None = None,
        free_lines: bool = False,
        start_timeout_s: float = 10.0,
    ) -> None:
        defaults = MCU_DEFAULTS.get(mcu)
        if pins is None or quiet_reg == "default":
            if defaults is None:
                raise DeviceError(
                    f"no default pins or quiet register for MCU {mcu!r} "
                    f"(known: {', '.join(MCU_DEFAULTS)}): pass pins= and quiet_reg="
                )
            pins = defaults.pins if pins is None else pins
            quiet_reg = defaults.quiet_reg if quiet_reg == "default" else quiet_reg
        self.clock: ClockMode = clock
        self.binary = binary if binary is not None else find_binary()
        args = [str(self.binary), "--elf", str(elf), "--mcu", mcu, "--freq", str(freq_hz), "--clock", clock]
        for name, where in pins.items():
            args += ["--pin", f"{name}={where}"]
        for name, where in (input_pins or {}).items():
            args += ["--input-pin", f"{name}={where}"]
        if edges_path is not None:
            args += ["--edges", str(edges_path)]
        if quiet_reg is not None:
            args += ["--quiet-reg", f"0x{quiet_reg[0]:X}:0x{quiet_reg[1]:X}"]
        if out_buffer is not None:  # bytes of firmware output held for the pty (default 1 MiB)
            args += ["--out-buffer", str(out_buffer)]
        if free_lines:  # FREE feeds the host's bytes a whole line at a time, each when idle
            args += ["--free-lines"]
        self._stderr_tail: deque[str] = deque(maxlen=STDERR_TAIL_LINES)
        self._buf = b""
        self._write_lock = threading.Lock()
        self._read_lock = threading.Lock()  # close() leaves stdout open under a reading free()
        self._closed = False
        self._exit_reported = False
        log.debug("starting %s", " ".join(args))
        self._proc = subprocess.Popen(
            args,
            stdin=subprocess.PIPE if clock == "control" else subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        # its stderr (lag and lost-byte reports, the reason it stopped) goes to this module's
        # log as it comes, and the last lines into error messages
        self._stderr_thread = threading.Thread(
            target=self._pump_stderr, name="avr_harness-stderr", daemon=True
        )
        self._stderr_thread.start()
        try:
            line = self._read_line(time.monotonic() + start_timeout_s)
            if not line.startswith("pty: /dev/"):
                raise ProtocolError(f"avr_harness's first line is not 'pty: /dev/...': {line!r}")
        except BaseException:
            self._kill_quietly()
            raise
        self.port_path: str = line.removeprefix("pty: ")
        log.info("avr_harness serves %s (%s, %s clock) on %s", elf, mcu, clock, self.port_path)

    # ------------------------------------------------------------------ process plumbing

    @property
    def returncode(self) -> int | None:
        """The harness's exit status, None while it runs."""
        return self._proc.poll()

    def stderr_tail(self) -> str:
        """The last lines the harness wrote on stderr (all of them once it has exited)."""
        if self._proc.poll() is not None:
            self._stderr_thread.join(5.0)
        return "\n".join(self._stderr_tail)

    def _pump_stderr(self) -> None:
        assert self._proc.stderr is not None
        for raw in self._proc.stderr:
            line = raw.decode(errors="replace").rstrip("\n")
            self._stderr_tail.append(line)
            if line.startswith("avr_harness: stopped by signal"):
                log.debug("%s", line)
            else:
                log.warning("%s", line)
        self._proc.stderr.close()

    def _exited_error(self, what: str) -> DeviceError:
        try:
            rc = self._proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            rc = None
        self._exit_reported = True
        return DeviceError(f"avr_harness {what} (exit status {rc}); its stderr ends:\n{self.stderr_tail()}")

    def _read_line(self, deadline: float | None) -> str:
        """One stdout line (without the newline); DeviceTimeoutError past the deadline."""
        with self._read_lock:
            return self._read_line_locked(deadline)

    def _read_line_locked(self, deadline: float | None) -> str:
        assert self._proc.stdout is not None
        fd = self._proc.stdout.fileno()
        while b"\n" not in self._buf:
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            ready, _, _ = select.select([fd], [], [], wait)
            if not ready:
                raise DeviceTimeoutError(
                    f"avr_harness said nothing for the deadline; its stderr ends:\n{self.stderr_tail()}"
                )
            chunk = os.read(fd, 65536)
            if not chunk:
                raise self._exited_error("closed its stdout")
            self._buf += chunk
        line, _, self._buf = self._buf.partition(b"\n")
        return line.decode()

    def _send(self, line: str) -> None:
        if self.clock != "control":
            raise DeviceError(f"avr_harness runs a {self.clock} clock: only a control clock takes commands")
        assert self._proc.stdin is not None
        with self._write_lock:
            try:
                self._proc.stdin.write(line.encode() + b"\n")
                self._proc.stdin.flush()
            except BrokenPipeError as exc:
                raise self._exited_error(f"is gone; it could not take {line!r}") from exc

    def _answer(self, command: str) -> tuple[str, list[Edge]]:
        """Send `command`; return its answer line (AT/OK) and the EDGE lines before it."""
        self._send(command)
        edges: list[Edge] = []
        while True:
            line = self._read_line(None)
            if line.startswith("EDGE "):
                edges.append(parse_edge_line(line.removeprefix("EDGE ")))
            elif line == "NOP":
                continue  # the answer to an interrupt() that came after its FREE had returned
            elif line.startswith("ERR "):
                raise ProtocolError(f"avr_harness refused {command!r}: {line.removeprefix('ERR ')}")
            else:
                return line, edges

    def _step(self, command: str) -> Step:
        line, edges = self._answer(command)
        parts = line.split()
        if (
            len(parts) not in (3, 4)
            or parts[0] != "AT"
            or not parts[1].isdigit()
            or parts[2] not in QUIET_WORDS
            or parts[3:] not in ([], ["host"])
        ):
            raise ProtocolError(
                f"avr_harness answered {command!r} with {line!r} (want 'AT <cycle> quiet|scheduled[ host]')"
            )
        return Step(int(parts[1]), parts[2] == "quiet", edges, len(parts) == 4)

    # ------------------------------------------------------------------ control clock

    def run_until(self, cycle: int) -> Step:
        """Run the AVR until its cycle counter reaches `cycle` (host bytes are served meanwhile)."""
        return self._step(f"RUN {cycle}")

    def free(self) -> Step:
        """Run while the firmware is quiet; time stands still while it also sleeps with the UART
        idle. Returns (not quiet) once it schedules something, or (quiet) when interrupt() or
        close() is called from another thread."""
        return self._step("FREE")

    def interrupt(self) -> None:
        """Make a blocking free() return (thread-safe); harmless when none is running."""
        self._send("NOP")

    def set_pin(self, cycle: int, name: str, value: int) -> None:
        """Drive input pin `name` to `value` at `cycle` (not in the past)."""
        line, edges = self._answer(f"SET {cycle} {name} {value}")
        if line != "OK" or edges:
            raise ProtocolError(f"avr_harness answered SET with {line!r} (want 'OK')")

    # ------------------------------------------------------------------ shutdown

    def close(self, timeout_s: float = 5.0) -> None:
        """End the harness: QUIT (control; a blocked free() returns quiet) or SIGTERM, then kill
        after `timeout_s`. A non-zero exit not reported yet raises DeviceError with its stderr."""
        if self._closed:
            return
        self._closed = True
        try:
            if self._proc.poll() is None:
                self._stop(timeout_s)
            rc = self._proc.wait()
            if rc != 0 and not self._exit_reported:
                self._exit_reported = True
                raise DeviceError(
                    f"avr_harness exited with status {rc}; its stderr ends:\n{self.stderr_tail()}"
                )
        finally:
            # a free() in another thread reads the answer to QUIT first (the pipe then ends)
            if self._proc.stdout is not None and self._read_lock.acquire(timeout=timeout_s):
                self._proc.stdout.close()
                self._read_lock.release()
            self._stderr_thread.join(5.0)

    def _stop(self, timeout_s: float) -> None:
        if self.clock == "control":
            assert self._proc.stdin is not None
            with self._write_lock:
                try:
                    self._proc.stdin.write(b"QUIT\n")
                    self._proc.stdin.close()
                except BrokenPipeError:
                    log.debug("avr_harness had already closed its stdin; its exit status says why")
        else:
            self._proc.terminate()
        try:
            self._proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            log.warning("avr_harness did not stop within %.1f s: killing it", timeout_s)
            self._proc.kill()
            self._proc.wait()

    def _kill_quietly(self) -> None:
        """Start-up failed: the error being raised says why; leave no process behind."""
        self._closed = True
        self._proc.kill()
        self._proc.wait()
        if self._proc.stdout is not None:
            self._proc.stdout.close()
        self._stderr_thread.join(5.0)

    def __enter__(self) -> AvrHarness:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
