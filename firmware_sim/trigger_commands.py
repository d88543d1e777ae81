"""What the simulated trigger-box firmware answers (docs/trigger-protocol.md): a host line is
checked (length, printable ASCII, `*HH` checksum, `#tag`), its command dispatched through
`_COMMANDS`, and each handler validates its arguments and the box state. `SimTriggerBox`
(firmware_sim.trigger_box) mixes this in and supplies the state, the link and the pulse
scheduler; an `ERR <code> <message>` reply is a `CommandError` raised here.
"""

from __future__ import annotations

import re
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from rigd.core.errors import DeviceError

if TYPE_CHECKING:
    from firmware_sim.world import SimWorld

VENDOR = "rigd-sim"
MODEL = "trigbox-sim"
FIRMWARE = "1.0.0"

#: Longest host->box line accepted, excluding the newline.
MAX_LINE = 64
#: Pulse records kept for readback (`TS?`).
RING_SIZE = 65536
#: Most records one `TS?` returns.
MAX_TS_COUNT = 64
MAX_RATE_HZ = 10_000.0
MIN_RATE_HZ = 0.001
MAX_WIDTH_US = 1_000_000
MAX_PULSES = 2**31 - 1
#: Longest text of ours an ERR line carries (a cable's socket path may be long).
MAX_ERR_TEXT = 400

_RATE_RE = re.compile(r"^\d{1,5}(\.\d{1,6})?$")
_UINT_RE = re.compile(r"^\d{1,10}$")

IDLE, ARMED, RUNNING = "IDLE", "ARMED", "RUNNING"


def _shown(text: str, limit: int = 16) -> str:
    """Host text quoted back in a reply: never the framing bytes '$' and '*', which a payload
    must not contain (docs/trigger-protocol.md, "Framing")."""
    return text[:limit].replace("$", "?").replace("*", "?")


def checksum(payload: bytes) -> int:
    """NMEA-style XOR of the payload bytes (between '$' and '*')."""
    x = 0
    for b in payload:
        x ^= b
    return x


class CommandError(Exception):
    """An `ERR <code> <message>` reply to send back."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code} {message}")
        self.code = code
        self.message = message


#: A box's edge jitter (its std) must be this many times smaller than the trigger period.
JITTER_PERIODS = 20


class BoxCommands:
    """The firmware's command set, mixed into `SimTriggerBox` (which owns what is declared here)."""

    world: SimWorld
    seed: int
    jitter_us: float
    tx_dropped: int
    commands_received: int
    _lock: threading.Lock
    _state: str
    _rate_hz: float
    _width_us: int
    _count: int
    _target: int
    _t0: int
    _ring: np.ndarray[Any, np.dtype[np.int64]]
    _run_stop: threading.Event
    _scheduler: threading.Thread | None
    _reply: Callable[[list[str], int | None], None]
    _reply_error: Callable[[CommandError, int | None], None]
    box_now: Callable[[], int]
    _first_pulse_time: Callable[[], int]
    _halt_scheduler: Callable[[], None]
    _pulse_loop: Callable[..., None]

    def _handle_line(self, raw: bytes) -> None:
        self.commands_received += 1
        if raw.endswith(b"\r"):
            raw = raw[:-1]
        if not raw:
            return
        tag: int | None = None
        try:
            if len(raw) > MAX_LINE:
                raise CommandError("TOOLONG", f"line exceeds {MAX_LINE} bytes")
            for col, b in enumerate(raw):
                if not 0x20 <= b <= 0x7E:
                    raise CommandError("BADCHAR", f"byte 0x{b:02X} at column {col} is not printable ASCII")
            text = raw.decode("ascii")
            if text.startswith("$"):
                text = text[1:]
            if "*" in text:
                text, hh = text.rsplit("*", 1)
                if not re.fullmatch(r"[0-9A-Fa-f]{2}", hh) or int(hh, 16) != checksum(text.encode()):
                    raise CommandError("CHECKSUM", f"checksum *{_shown(hh, 8)} does not match the line")
            tokens = text.split()
            if tokens and tokens[-1].startswith("#"):
                tag_text = tokens.pop()[1:]
                if not _UINT_RE.match(tag_text) or int(tag_text) > 65535:
                    raise CommandError("BADARG", f"tag #{_shown(tag_text)} is not an integer 0..65535")
                tag = int(tag_text)
            if not tokens:
                raise CommandError("UNKNOWN", "empty command")
            self._reply(self._dispatch(tokens[0].upper(), tokens[1:]), tag)
        except CommandError as err:
            self._reply_error(err, tag)

    # ---------------------------------------------------------------- commands
    def _dispatch(self, cmd: str, args: list[str]) -> list[str]:
        handler = _COMMANDS.get(cmd)
        if handler is None:
            raise CommandError("UNKNOWN", f"unknown command {_shown(cmd)!r}")
        name, min_args, max_args = handler
        if not min_args <= len(args) <= max_args:
            want = str(min_args) if min_args == max_args else f"{min_args}..{max_args}"
            raise CommandError("BADARG", f"{cmd} takes {want} argument(s), got {len(args)}")
        result: list[str] = getattr(self, name)(args)
        return result

    def _cmd_ping(self, args: list[str]) -> list[str]:
        return ["PONG"]

    def _cmd_id(self, args: list[str]) -> list[str]:
        return [f"ID {VENDOR} {MODEL} SIM{self.seed:04d} {FIRMWARE}"]

    def _cmd_rate(self, args: list[str]) -> list[str]:
        text = args[0]
        if not _RATE_RE.match(text) or not MIN_RATE_HZ <= float(text) <= MAX_RATE_HZ:
            raise CommandError(
                "BADARG", f"rate {_shown(text)!r} not a decimal in {MIN_RATE_HZ}..{MAX_RATE_HZ:g} Hz"
            )
        period_us = 1e6 / float(text)
        if self.jitter_us * JITTER_PERIODS > period_us:
            # Edges that jitter by a sizeable part of the period land in the wrong period (or
            # far in the future): the sim refuses the rate rather than fire nonsense.
            raise CommandError(
                "BADARG",
                f"rate {text[:16]} Hz: its {period_us:.0f} us period is not {JITTER_PERIODS}x the "
                f"box's edge jitter_us={self.jitter_us:g}",
            )
        with self._lock:
            if self._state == RUNNING:
                raise CommandError("STATE", "RATE not allowed while RUNNING")
            self._rate_hz = float(text)
            return [f"OK RATE {self._rate_hz:.6f}"]

    def _cmd_width(self, args: list[str]) -> list[str]:
        text = args[0]
        if not _UINT_RE.match(text) or not 1 <= int(text) <= MAX_WIDTH_US:
            raise CommandError("BADARG", f"width {_shown(text)!r} not an integer in 1..{MAX_WIDTH_US} us")
        with self._lock:
            if self._state == RUNNING:
                raise CommandError("STATE", "WIDTH not allowed while RUNNING")
            self._width_us = int(text)
            return [f"OK WIDTH {self._width_us}"]

    def _cmd_arm(self, args: list[str]) -> list[str]:
        with self._lock:
            if self._state == RUNNING:
                raise CommandError("STATE", "ARM not allowed while RUNNING")
            self._state = ARMED
            self._count = 0
            self._target = 0
            self._t0 = -1
            return ["OK ARM"]

    def _cmd_start(self, args: list[str]) -> list[str]:
        target = 0
        if args:
            if not _UINT_RE.match(args[0]) or not 1 <= int(args[0]) <= MAX_PULSES:
                raise CommandError(
                    "BADARG", f"pulse count {_shown(args[0])!r} not an integer in 1..{MAX_PULSES}"
                )
            target = int(args[0])
        with self._lock:
            if self._state != ARMED:
                raise CommandError("STATE", f"START needs ARMED, box is {self._state}")
        try:
            self.world.await_cable()  # a cable lead's followers must hear the run from its start
        except DeviceError as exc:
            raise CommandError("STATE", _shown(str(exc), MAX_ERR_TEXT)) from None
        with self._lock:
            if self._state != ARMED:
                raise CommandError("STATE", f"START needs ARMED, box is {self._state}")
            period = 1e6 / self._rate_hz
            if self._width_us >= period:
                raise CommandError("BADARG", f"width {self._width_us} us >= period {period:.1f} us")
            self._t0 = self._first_pulse_time()
            self._target = target
            self._state = RUNNING
            self._run_stop = threading.Event()
            self._scheduler = threading.Thread(
                target=self._pulse_loop,
                args=(self._t0, self._rate_hz, self._width_us, target, self._run_stop, self.world.hold()),
                name=f"trigbox-pulses-{self.world.name}",
                daemon=True,
            )
            self._scheduler.start()
        self.world.clock.start()  # a virtual world's time runs from the first START
        return [f"OK START {self._t0} {target}"]

    def _cmd_stop(self, args: list[str]) -> list[str]:
        self._halt_scheduler()
        with self._lock:
            if self._state != IDLE:
                self._state = IDLE
            return [f"OK STOP {self._count}"]

    def _cmd_count(self, args: list[str]) -> list[str]:
        with self._lock:
            return [f"COUNT {self._count}"]

    def _cmd_status(self, args: list[str]) -> list[str]:
        with self._lock:
            return [
                f"STATUS {self._state} count={self._count} target={self._target} "
                f"rate={self._rate_hz:.6f} width={self._width_us} t0={self._t0}"
            ]

    def _cmd_clock(self, args: list[str]) -> list[str]:
        return [f"CLOCK {self.box_now()}"]

    def _cmd_diag(self, args: list[str]) -> list[str]:
        with self._lock:
            return [f"DIAG records_dropped={self.tx_dropped} rx_lost=0 late_edges=0"]

    def _cmd_ts(self, args: list[str]) -> list[str]:
        first_text, count_text = args
        if not _UINT_RE.match(first_text):
            raise CommandError("BADARG", f"first index {_shown(first_text)!r} not a non-negative integer")
        if not _UINT_RE.match(count_text) or not 1 <= int(count_text) <= MAX_TS_COUNT:
            raise CommandError("BADARG", f"count {_shown(count_text)!r} not an integer in 1..{MAX_TS_COUNT}")
        first, count = int(first_text), int(count_text)
        with self._lock:
            lo = max(first, self._count - RING_SIZE)
            hi = min(first + count, self._count)
            lines = [f"T {k} {int(self._ring[k % RING_SIZE])}" for k in range(lo, hi)]
        return [*lines, f"OK TS {len(lines)}"]


_COMMANDS: dict[str, tuple[str, int, int]] = {
    "PING": ("_cmd_ping", 0, 0),
    "ID?": ("_cmd_id", 0, 0),
    "RATE": ("_cmd_rate", 1, 1),
    "WIDTH": ("_cmd_width", 1, 1),
    "ARM": ("_cmd_arm", 0, 0),
    "START": ("_cmd_start", 0, 1),
    "STOP": ("_cmd_stop", 0, 0),
    "COUNT?": ("_cmd_count", 0, 0),
    "STATUS?": ("_cmd_status", 0, 0),
    "CLOCK?": ("_cmd_clock", 0, 0),
    "TS?": ("_cmd_ts", 2, 2),
    "DIAG?": ("_cmd_diag", 0, 0),
}
