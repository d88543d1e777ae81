"""Simulated trigger-box firmware on a pseudo-terminal (or a socket pair, for HID).

The box speaks the protocol of docs/trigger-protocol.md on the master side of a pty; the
host opens the slave (`port_path`) with pyserial exactly as it would open a USB-serial box,
so the real driver (`drivers.serial_trigger`) is what the tests exercise. The box clock is
a `DeviceClock` registered in the world as "trigger": it is the rig timebase.

Pulse k of a run is scheduled at box time b_k = t0 + round(k * 1e6 / rate); the box reports
b_k, while the physical edge leaves at the true time of b_k plus Gaussian jitter the box
cannot know. The schedule is computed, never measured, so OS sleep error never leaks into
timestamps (a late wake-up only delays the report).

With `link="socket"` the firmware talks over one end of a socket pair instead of a pty;
`host_socket` is the other end, a plain byte pipe that `firmware_sim.hid_box` packs into
HID reports, so the same firmware serves the HID transport.

Link faults (docs/sim-faults.md) leave the electrical trigger running: `silent_after=N` hangs
the link after N pulses (nothing more is sent, nothing received: a hung USB-serial bridge),
`garbage_after=N` turns every line sent after N pulses into garbage bytes (a baud-rate or
bridge fault). Pulse records written to the link go to the ground-truth journal when
`RIGD_SIM_TRUTH_LOG` is set.

Here: the link, the state and the pulse scheduler; the command set (line checks, dispatch,
argument and state validation) is `firmware_sim.trigger_commands.BoxCommands`.
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import select
import socket
import struct
import termios
import threading
import time
import tty
from collections.abc import Iterable
from typing import Literal

import numpy as np

from firmware_sim.cable import CABLE_PARAMS
from firmware_sim.clock import Hold
from firmware_sim.trigger_commands import (
    FIRMWARE,
    IDLE,
    MAX_LINE,
    MODEL,
    RING_SIZE,
    BoxCommands,
    CommandError,
    checksum,
)
from firmware_sim.world import DeviceClock, Edge, SimWorld, truth_journal
from rigd.core.errors import ConfigError
from rigd.core.timebase import pulse_offset_us

log = logging.getLogger(__name__)

#: Lead between START and pulse 0, in box microseconds: time to reply and arm the timer.
START_LEAD_US = 20_000
#: Bytes the garbage fault may inject: never '$', '*' or newline, so framing survives.
_GARBAGE_BYTES = bytes(b for b in range(256) if b not in b"$*\n")
_GARBAGE_ARRAY = np.frombuffer(_GARBAGE_BYTES, np.uint8)
_CORRUPT_CHARS = b"ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789#=-. "
#: Virtual time: how long (wall s) a pulse holds the world for the host to read its record,
#: and how often it looks (`SimTriggerBox._wait_host_read`).
_HOST_READ_WAIT_S = 0.5
_HOST_READ_POLL_S = 0.0002

#: What became of a line the box meant to send.
SendResult = Literal["sent", "garbled", "dropped", "silent"]


def frame(payload: str) -> bytes:
    """A box->host line: `$<payload>*HH\\n`."""
    data = payload.encode("ascii")
    return b"$" + data + b"*%02X\n" % checksum(data)


class SimTriggerBox(BoxCommands):
    """Trigger-box firmware running in two threads on the master side of a pty."""

    def __init__(
        self,
        world: SimWorld,
        *,
        offset_us: float = 0.0,
        drift_ppm: float = 0.0,
        jitter_us: float = 0.0,
        drop_pulses: Iterable[int] = (),
        garbage_every: int = 0,
        boot_ms: int = 50,
        seed: int = 0,
        link: Literal["pty", "socket"] = "pty",
        silent_after: int = 0,
        garbage_after: int = 0,
    ) -> None:
        if not jitter_us >= 0 or garbage_every < 0 or boot_ms < 0:
            raise ConfigError("sim trigger box: jitter_us, garbage_every and boot_ms must be >= 0")
        for name, value in (("silent_after", silent_after), ("garbage_after", garbage_after)):
            if value < 0:
                raise ConfigError(f"sim trigger box: {name} must be >= 0 (0: off), got {value}")
        self.world = world
        self.clock = DeviceClock(offset_us, drift_ppm)
        world.register_clock("trigger", self.clock)
        self.jitter_us = float(jitter_us)
        self.drop_pulses = frozenset(int(i) for i in drop_pulses)
        self.garbage_every = int(garbage_every)
        self.boot_ms = int(boot_ms)
        self.seed = int(seed)
        self.silent_after = int(silent_after)
        self.garbage_after = int(garbage_after)
        #: Link hung (`silent_after` reached): nothing is sent, received bytes are discarded.
        self.silent = False
        #: Link garbled (`garbage_after` reached): every line sent is garbage bytes.
        self.garbage = False
        #: Pulses fired since power-up, over all runs (the `*_after` faults count these).
        self.pulses_fired = 0
        self._journal = truth_journal()
        self._journal_head = f'{{"world":{json.dumps(world.name)},"dev":"trigger","kind":"pulse"'
        #: Test switch: while True the box reads commands but never answers (a hung box).
        self.mute = False
        #: Test switch: swallow this many next replies (a reply lost on the wire).
        self.drop_replies = 0
        self._jitter_rng = np.random.default_rng([self.seed, 0])
        self._garbage_rng = np.random.default_rng([self.seed, 1])

        self._lock = threading.Lock()  # state, ring buffer and the tx side of the pty
        self._state = IDLE
        self._rate_hz = 30.0
        self._width_us = 1000
        self._count = 0
        self._target = 0
        self._t0 = -1
        self._ring = np.zeros(RING_SIZE, np.int64)
        self._lines_sent = 0
        self._bytes_sent = 0
        #: What the host's link reported handled (`host_handled`); None: it reports nothing.
        self._handled: int | None = None
        self._handled_cond = threading.Condition()
        self.tx_dropped = 0
        self.commands_received = 0
        #: ERR codes the box has replied with, in order (tests read it).
        self.errors_sent: list[str] = []
        self.booted = threading.Event()

        self._stop = threading.Event()
        self._run_stop = threading.Event()
        self._scheduler: threading.Thread | None = None
        self._closed = False

        #: Host end of the socket link (None on a pty: the host opens `port_path`).
        self.host_socket: socket.socket | None = None
        self._box_socket: socket.socket | None = None
        if link == "socket":
            self._box_socket, self.host_socket = socket.socketpair()
            self._master = self._slave = self._box_socket.fileno()
            self.port_path = f"socket:{world.name}"
        else:
            self._master, self._slave = os.openpty()
            # Raw on both ends: no echo of what the box writes, no CR/LF translation, even
            # before the host has opened and configured the slave.
            tty.setraw(self._master)
            tty.setraw(self._slave)
            self.port_path = os.ttyname(self._slave)
        os.set_blocking(self._master, False)
        self._boot_deadline = time.monotonic() + self.boot_ms / 1000.0
        self._reader = threading.Thread(target=self._read_loop, name=f"trigbox-rx-{world.name}", daemon=True)
        self._reader.start()
        log.info("sim trigger box for world %r on %s", world.name, self.port_path)

    # ---------------------------------------------------------------- clock, state
    def box_now(self) -> int:
        """The box's free-running microsecond counter now."""
        return self.clock.stamp(self.world.now_us())

    @property
    def state(self) -> str:
        with self._lock:
            return self._state

    @property
    def count(self) -> int:
        with self._lock:
            return self._count

    @property
    def closed(self) -> bool:
        return self._closed

    # ---------------------------------------------------------------- tx
    def _send_locked(self, payload: str) -> SendResult:
        """Write one framed line (caller holds the lock); drop it if the host stops reading."""
        if self.silent:
            return "silent"
        data = frame(payload)
        self._lines_sent += 1
        result: SendResult = "sent"
        if self.garbage:
            data = self._garble(data)
            result = "garbled"
        elif self.garbage_every and self._lines_sent % self.garbage_every == 0:
            data = self._corrupt(data)
            result = "garbled"
        view = memoryview(data)
        deadline = time.monotonic() + 0.05
        while view:
            try:
                n = os.write(self._master, view)
                view = view[n:]
                self._bytes_sent += n
            except BlockingIOError:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    self.tx_dropped += 1
                    log.warning("trigger box %s: host not reading, line dropped: %r", self.port_path, payload)
                    return "dropped"
                select.select([], [self._master], [], remaining)
            except OSError as exc:
                if self._closed:
                    return "dropped"
                log.error("trigger box %s: write failed: %s", self.port_path, exc)
                raise
        return result

    def _garble(self, data: bytes) -> bytes:
        """`garbage_after` fault: the whole line becomes random bytes (no '$', so never a line)."""
        idx = self._garbage_rng.integers(0, len(_GARBAGE_ARRAY), len(data) - 1)
        return _GARBAGE_ARRAY[idx].tobytes() + b"\n"

    def _corrupt(self, data: bytes) -> bytes:
        """Garbage fault: random prefix bytes, and sometimes one wrong character inside."""
        rng = self._garbage_rng
        n = int(rng.integers(1, 7))
        prefix = bytes(_GARBAGE_BYTES[int(i)] for i in rng.integers(0, len(_GARBAGE_BYTES), n))
        if rng.random() < 0.5:
            star = data.rindex(b"*")
            pos = int(rng.integers(1, star))
            old = data[pos]
            choices = [c for c in _CORRUPT_CHARS if c != old]
            new = choices[int(rng.integers(0, len(choices)))]
            data = data[:pos] + bytes([new]) + data[pos + 1 :]
        return prefix + data

    # ---------------------------------------------------------------- rx
    def _read_loop(self) -> None:
        buf = bytearray()
        discarding = False
        while not self._stop.is_set():
            timeout = 0.05
            if not self.booted.is_set():
                until_boot = self._boot_deadline - time.monotonic()
                if until_boot <= 0:
                    with self._lock:
                        self._send_locked(f"READY {MODEL} {FIRMWARE}")
                    self.booted.set()
                    log.debug("trigger box %s booted", self.port_path)
                else:
                    timeout = min(timeout, until_boot)
            try:
                ready, _, _ = select.select([self._master], [], [], timeout)
                if not ready:
                    continue
                chunk = os.read(self._master, 4096)
            except BlockingIOError:
                continue
            except OSError as exc:
                if self._stop.is_set() or exc.errno == errno.EBADF:
                    return
                if exc.errno == errno.ECONNRESET:  # socket link: the host end is gone
                    time.sleep(0.01)
                    continue
                if exc.errno == errno.EIO:  # no slave fd open: cannot happen while we hold one
                    time.sleep(0.01)
                    continue
                log.error("trigger box %s: read failed: %s", self.port_path, exc)
                raise
            if not chunk:  # socket link whose host end shut down: nothing more will come
                time.sleep(0.01)
                continue
            if not self.booted.is_set():
                continue  # still booting: the UART is not listening yet
            if self.silent:
                continue  # hung bridge: what the host sends never reaches the firmware
            for byte in chunk:
                if byte == 0x0A:
                    line = bytes(buf)
                    buf.clear()
                    if discarding:
                        discarding = False
                        self._reply_error(CommandError("TOOLONG", f"line exceeds {MAX_LINE} bytes"), None)
                    else:
                        self._handle_line(line)
                elif not discarding:
                    buf.append(byte)
                    if len(buf) > MAX_LINE + 1:  # +1 tolerates a trailing CR
                        buf.clear()
                        discarding = True

    def _reply(self, lines: list[str], tag: int | None) -> None:
        if self.mute:
            return
        if self.drop_replies > 0:
            self.drop_replies -= 1
            log.debug("trigger box %s: dropping reply %r (test switch)", self.port_path, lines)
            return
        suffix = f" #{tag}" if tag is not None else ""
        with self._lock:
            for line in lines:
                self._send_locked(line + suffix)

    def _reply_error(self, err: CommandError, tag: int | None) -> None:
        log.debug("trigger box %s: ERR %s %s", self.port_path, err.code, err.message)
        self.errors_sent.append(err.code)
        self._reply([f"ERR {err.code} {err.message}"], tag)

    # ---------------------------------------------------------------- pulses
    def _first_pulse_time(self) -> int:
        """Box time of pulse 0 of a run STARTed now (a replayed box puts its recording there)."""
        return self.box_now() + START_LEAD_US

    def _pulse_box_time(self, t0: int, rate_hz: float, k: int) -> int | None:
        """Box time of pulse k of the run; None when the schedule has no more (a replay's end).

        The exact rational with halves rounded up, in integers: the same b_k as the AVR
        firmware (docs/trigger-protocol.md, "Pulses")."""
        return t0 + pulse_offset_us(k, rate_hz)

    def _halt_scheduler(self) -> None:
        sched = self._scheduler
        self._run_stop.set()
        self._wake_waiter()
        if sched is not None and sched is not threading.current_thread():
            sched.join()
        self._scheduler = None

    def _pulse_loop(
        self, t0: int, rate_hz: float, width_us: int, target: int, stop: threading.Event, hold: Hold
    ) -> None:
        """The box timer. `hold` keeps a virtual world's time at each pulse until its edges
        are on the wire (the devices take their own holds as they latch them)."""
        k = 0
        try:
            while not target or k < target:
                b_k = self._pulse_box_time(t0, rate_hz, k)
                if b_k is None:
                    with self._lock:
                        self._state = IDLE
                        self._send_locked(f"END {self._count}")
                    log.info("trigger box %s: schedule ended after %d pulses", self.port_path, k)
                    return
                true_us = self.clock.true_at(b_k)
                if not hold.sleep_until(true_us, stop):
                    return
                jitter = float(self._jitter_rng.normal(0.0, self.jitter_us)) if self.jitter_us else 0.0
                edge = true_us + jitter
                delivered = k not in self.drop_pulses
                if delivered:
                    self.world.wire.fire(Edge(rising=True, true_us=edge, pulse_index=k))
                    self.world.wire.fire(Edge(rising=False, true_us=edge + width_us, pulse_index=k))
                self.world.truth.add_pulse(k, b_k, edge, delivered)
                with self._lock:
                    if stop.is_set():  # STOP raced the edge: the pulse went out, report it
                        log.debug("trigger box %s: pulse %d fired as STOP arrived", self.port_path, k)
                    self._ring[k % RING_SIZE] = b_k
                    self._count = k + 1
                    sent = self._send_locked(f"P {k} {b_k}")
                    sent_bytes = self._bytes_sent
                    if self._journal is not None and sent in ("sent", "garbled"):
                        garbled = "true" if sent == "garbled" else "false"
                        self._journal.write(
                            f'{self._journal_head},"index":{k},"t_us":{b_k},'
                            f'"host_time_ns":{self.world.host_clock.now_ns()},"garbled":{garbled}}}'
                        )
                    self._link_faults_after_pulse()
                    if target and self._count >= target:
                        self._state = IDLE
                        self._send_locked(f"END {self._count}")
                if self.world.virtual and sent != "silent":
                    self._wait_host_read(k, sent_bytes, stop)
                k += 1
        except Exception:
            log.exception("trigger box %s: pulse scheduler failed at pulse %d", self.port_path, k)
            with self._lock:
                self._state = IDLE
            raise
        finally:
            hold.release()

    def host_handled(self, n_bytes: int) -> None:
        """The host's link (`firmware_sim.box_link`, the fake HID device): the first `n_bytes`
        the box sent have been read and every line among them handled (stamped)."""
        with self._handled_cond:
            self._handled = max(n_bytes, self._handled or 0)
            self._handled_cond.notify_all()

    def _wait_host_read(self, k: int, sent_bytes: int, stop: threading.Event) -> None:
        """Virtual time: hold the world at the pulse until the host has stamped its record (at
        most `_HOST_READ_WAIT_S` of wall time), so the record's host time is the pulse's virtual
        instant, as a USB link delivers it within a millisecond. Left to run on, the world's
        time would race ahead while the line sits unread on a loaded machine, and the records'
        host times would lag the devices' (stamped at their own virtual instants) by however
        long the host took: the coarse placement needs the fastest records prompt. A host link
        that reports what it handled is waited for exactly; any other reader until the line has
        left the kernel's queue (it may stamp a moment later)."""
        deadline = time.monotonic() + _HOST_READ_WAIT_S
        with self._handled_cond:
            if self._handled is not None:
                if not self._handled_cond.wait_for(
                    lambda: (self._handled or 0) >= sent_bytes or stop.is_set(), _HOST_READ_WAIT_S
                ):
                    log.debug(
                        "trigger box %s: record %d not handled in time; time goes on", self.port_path, k
                    )
                return
        while (unread := self._host_unread()) > 0 and not stop.is_set():
            if time.monotonic() >= deadline:
                log.debug(
                    "trigger box %s: record %d still unread (%d bytes); time goes on",
                    self.port_path,
                    k,
                    unread,
                )
                return
            time.sleep(_HOST_READ_POLL_S)

    def _wake_waiter(self) -> None:
        """A pulse waiting for the host to read its record stops waiting (STOP, close)."""
        with self._handled_cond:
            self._handled_cond.notify_all()

    def _host_unread(self) -> int:
        """Bytes the box sent that the host has not read yet (0 once closed)."""
        fd = self._slave if self.host_socket is None else self.host_socket.fileno()
        try:
            return int(struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0])
        except OSError:
            return 0  # closed under us: nobody will read it

    def _link_faults_after_pulse(self) -> None:
        """Count a fired pulse and switch the link faults on once due (caller holds the lock)."""
        self.pulses_fired += 1
        if self.silent_after and not self.silent and self.pulses_fired >= self.silent_after:
            self.silent = True
            log.warning(
                "trigger box %s: link hung after %d pulses (silent_after); trigger keeps firing",
                self.port_path,
                self.pulses_fired,
            )
        if self.garbage_after and not self.garbage and self.pulses_fired >= self.garbage_after:
            self.garbage = True
            log.warning(
                "trigger box %s: link sends garbage after %d pulses (garbage_after); trigger keeps firing",
                self.port_path,
                self.pulses_fired,
            )

    # ---------------------------------------------------------------- lifecycle
    def close(self) -> None:
        """Stop both threads and close the pty. Idempotent."""
        if self._closed:
            return
        self._stop.set()
        self._run_stop.set()
        self._wake_waiter()
        self._reader.join()
        sched = self._scheduler
        if sched is not None:
            sched.join()
        self._closed = True
        if self._box_socket is not None and self.host_socket is not None:
            self._box_socket.close()
            self.host_socket.close()
        else:
            for fd in (self._master, self._slave):
                try:
                    os.close(fd)
                except OSError as exc:
                    log.warning("trigger box %s: closing fd %d: %s", self.port_path, fd, exc)
        log.info("sim trigger box on %s closed", self.port_path)

    def __enter__(self) -> SimTriggerBox:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


#: Spec parameters of a box on the pty (sim and replay alike).
BOX_PARAMS = {
    "offset_us",
    "drift_ppm",
    "jitter_us",
    "drop_pulses",
    "garbage_every",
    "boot_ms",
    "seed",
    "transport",
    "silent_after",
    "garbage_after",
    "reply_timeout_s",
    "boot_timeout_s",
    "clock",
    *CABLE_PARAMS,
}
