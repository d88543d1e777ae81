"""The line layer of the trigger-box protocol (docs/trigger-protocol.md), whatever carries its bytes.

Framing (`$payload*HH`), checksums, tagged commands (`#n`) and their replies, retries of
idempotent commands after line noise, and the PING / READY handshake. The receive side splits
what the transport delivers into lines: pulse records (`P <index> <t_us>`) go to the device's
pulse queue stamped with its host clock (the monotonic clock, or a simulated world's), `END`
sets the run's final count, everything else goes to the reply queue a command waits on.
`SerialTrigger` (drivers.serial_trigger) is a `BoxLines` with the trigger's run semantics on top.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass

from drivers.lifecycle import END, Acquisition, Signal
from drivers.trigger_link import Transport, TransportError
from rigd.core.errors import DeviceTimeoutError, ProtocolError
from rigd.core.host_clock import HostClock

log = logging.getLogger(__name__)

#: After a corrupt line arrives during a command, how long to wait for a good reply before retrying.
_CORRUPT_GRACE_S = 0.15
_HANDSHAKE_PERIOD_S = 0.1
#: Bytes without a newline after which the receive buffer is noise, not a protocol line.
_MAX_LINE_BYTES = 4096


class TriggerBoxError(ProtocolError):
    """The box answered `ERR <code> <message>` to a command."""

    def __init__(self, port: str, command: str, code: str, message: str) -> None:
        super().__init__(f"trigger box {port}: {command!r} failed: ERR {code} {message}")
        self.port = port
        self.command = command
        self.code = code
        self.box_message = message


@dataclass(frozen=True, slots=True)
class _Reply:
    fields: list[str]
    tag: int | None
    line: str

    @property
    def is_error(self) -> bool:
        return self.fields[0] == "ERR"


def _checksum(payload: bytes) -> int:
    x = 0
    for b in payload:
        x ^= b
    return x


def _frame_command(payload: str) -> bytes:
    data = payload.encode("ascii")
    return data + b"*%02X\n" % _checksum(data)


class BoxLines:
    """The protocol's line layer, mixed into the device class that owns the receive thread.

    The device calls `_open_lines` before its receive thread starts, runs `_grab` on that thread
    (an `Acquisition` whose queue takes the pulse records), and says through `_check` whether it
    can still talk (closed, link lost)."""

    port: str
    reply_timeout_s: float
    _rx_thread: Acquisition[tuple[int, int, int]]
    _stats_lock: threading.Lock
    _stats: dict[str, int]
    _final_count: int | None
    host_clock: HostClock

    def _open_lines(self, transport: Transport, reply_timeout_s: float, host_clock: HostClock) -> None:
        self.host_clock = host_clock
        self._transport = transport
        self.port = transport.name
        self.reply_timeout_s = reply_timeout_s
        self._cmd_lock = threading.Lock()
        self._replies: queue.Queue[_Reply] = queue.Queue()
        self._rx = bytearray()
        self._corrupt_seen = 0  # bumps on every corrupt line; waiters compare before/after
        self._ready = threading.Event()
        self._handshake_done = False
        self._tag = 0

    def _check(self) -> None:
        """Raise when the device can no longer send commands; the device class says how."""
        raise NotImplementedError

    # ------------------------------------------------------------------ receive side
    def _grab(self, timeout_s: float) -> Signal | None:
        """Receive thread: split what arrived into lines and route them; pulse records go to
        the pulse queue (stamped with the host clock), replies to the reply queue."""
        try:
            chunk = self._transport.read(timeout_s)
        except TransportError as exc:
            if self._rx_thread.stopping.is_set():  # the link closed under us while closing: benign
                log.debug("trigger box %s: reader ends on close: %s", self.port, exc)
                return END
            raise  # kept: every later call says the box is disconnected
        if not chunk:
            return None
        buf = self._rx
        buf.extend(chunk)
        while (nl := buf.find(b"\n")) >= 0:
            line = bytes(buf[:nl])
            del buf[: nl + 1]
            try:
                self._handle_line(line)
            except (ProtocolError, ValueError, IndexError) as exc:
                log.exception("trigger box %s: cannot handle line %r", self.port, line)
                with self._stats_lock:
                    self._stats["bad_records"] += 1
                self._rx_thread.fail(exc)
        if len(buf) > _MAX_LINE_BYTES:  # no newline in 4 KiB: noise, not a protocol line
            with self._stats_lock:
                self._stats["garbage_bytes"] += len(buf)
                self._stats["corrupt_lines"] += 1
                self._corrupt_seen += 1
            buf.clear()
        return None

    def _corrupt(self, line: bytes, why: str) -> None:
        log.warning("trigger box %s: dropped corrupt line (%s): %r", self.port, why, line)
        with self._stats_lock:
            self._stats["corrupt_lines"] += 1
            self._corrupt_seen += 1

    def _handle_line(self, raw: bytes) -> None:
        host_ns = self.host_clock.now_ns()
        if raw.endswith(b"\r"):
            raw = raw[:-1]
        if not raw:
            return
        start = raw.rfind(b"$")
        if start < 0:
            self._corrupt(raw, "no '$' start")
            return
        if start:
            with self._stats_lock:
                self._stats["garbage_bytes"] += start
        sentence = raw[start + 1 :]
        star = sentence.rfind(b"*")
        if star < 0 or len(sentence) - star != 3:
            self._corrupt(raw, "no '*HH' checksum")
            return
        payload, hh = sentence[:star], sentence[star + 1 :]
        try:
            expected = int(hh, 16)
        except ValueError:
            self._corrupt(raw, "checksum is not hex")
            return
        if _checksum(payload) != expected or any(not 0x20 <= b <= 0x7E for b in payload):
            self._corrupt(raw, "checksum mismatch")
            return
        fields = payload.decode("ascii").split()
        if not fields:
            self._corrupt(raw, "empty payload")
            return
        with self._stats_lock:
            self._stats["lines"] += 1
        kind = fields[0]
        if kind == "P":
            if len(fields) != 3:
                raise ProtocolError(f"trigger box {self.port}: malformed pulse record {raw!r}")
            with self._stats_lock:
                self._stats["pulses_received"] += 1
            if self._rx_thread.queue.put((int(fields[1]), int(fields[2]), host_ns)) is not None:
                log.warning(
                    "trigger box %s: pulse queue full; record %s will be read back", self.port, fields[1]
                )
        elif kind == "END":
            with self._stats_lock:
                self._final_count = int(fields[1])
            log.debug("trigger box %s: run ended after %s pulses", self.port, fields[1])
        elif kind == "READY":
            if self._handshake_done:
                raise ProtocolError(f"trigger box {self.port} rebooted (unexpected {payload.decode()!r})")
            self._ready.set()
        else:
            tag: int | None = None
            if fields[-1].startswith("#"):
                tag = int(fields.pop()[1:])
            self._replies.put(_Reply(fields, tag, payload.decode("ascii")))

    # ------------------------------------------------------------------ commands
    def _check_present(self) -> None:
        """The receive side's kept error: a lost link, or a line that broke the protocol."""
        err = self._rx_thread.error
        if isinstance(err, TransportError):
            raise TransportError(
                f"trigger box {self.port} disconnected or failed (reopen it to continue): {err}"
            ) from err
        if err is not None:
            raise ProtocolError(f"trigger box {self.port}: receive side failed: {err}") from err

    def _write(self, payload: str) -> None:
        # An empty payload is a bare newline (it flushes a half line out of the box's buffer;
        # the box ignores empty lines). With a checksum it would be an empty command.
        data = _frame_command(payload) if payload else b"\n"
        try:
            self._transport.write(data)
        except TransportError as exc:
            raise TransportError(f"trigger box {self.port}: writing {payload!r} failed: {exc}") from exc

    def _next_tag(self) -> int:
        self._tag = self._tag % 65535 + 1
        return self._tag

    def _drain_replies(self) -> None:
        while True:
            try:
                stale = self._replies.get_nowait()
            except queue.Empty:
                return
            log.debug("trigger box %s: discarding stale reply %r", self.port, stale.line)
            with self._stats_lock:
                self._stats["stale_replies"] += 1

    def _command(self, command: str, *, idempotent: bool, retries: int = 2) -> list[_Reply]:
        """Send a command and collect its reply lines (the last is the final one).

        A corrupt line during the wait may have been our reply: idempotent commands are
        resent then; others raise DeviceTimeoutError for the caller to resolve.
        """
        with self._cmd_lock:
            for attempt in range(retries + 1):
                self._check()
                tag = self._next_tag()
                self._drain_replies()
                corrupt_before = self._corrupt_seen
                self._write(f"{command} #{tag}")
                result = self._await_reply(command, tag, corrupt_before)
                if result is not None:
                    return result
                corrupted = self._corrupt_seen != corrupt_before
                if not (corrupted and idempotent and attempt < retries):
                    why = " (a corrupt line arrived meanwhile)" if corrupted else ""
                    raise DeviceTimeoutError(
                        f"trigger box {self.port}: no reply to {command!r} "
                        f"within {self.reply_timeout_s:g} s{why}"
                    )
                log.info("trigger box %s: reply to %r lost to line noise, resending", self.port, command)
                with self._stats_lock:
                    self._stats["retries"] += 1
        raise AssertionError("unreachable")

    def _await_reply(self, command: str, tag: int, corrupt_before: int) -> list[_Reply] | None:
        deadline = time.monotonic() + self.reply_timeout_s
        grace_set = False
        lines: list[_Reply] = []
        while True:
            if not grace_set and self._corrupt_seen != corrupt_before:
                grace_set = True
                deadline = min(deadline, time.monotonic() + _CORRUPT_GRACE_S)
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            try:
                reply = self._replies.get(timeout=min(remaining, 0.02))
            except queue.Empty:
                self._check()
                continue
            if reply.tag is None and reply.is_error:
                # The box could not parse our line at all (noise on the way in): it is ours.
                pass
            elif reply.tag != tag:
                log.debug(
                    "trigger box %s: stale reply %r while waiting for %r", self.port, reply.line, command
                )
                with self._stats_lock:
                    self._stats["stale_replies"] += 1
                continue
            if reply.is_error:
                code = reply.fields[1] if len(reply.fields) > 1 else "?"
                raise TriggerBoxError(self.port, command, code, " ".join(reply.fields[2:]))
            lines.append(reply)
            if reply.fields[0] != "T":  # T lines precede the final OK TS line
                return lines

    def _handshake(self, timeout_s: float) -> None:
        """PING until PONG or READY, with a deadline: no fixed boot sleep."""
        deadline = time.monotonic() + timeout_s
        self._write("")  # a bare newline ends any half line left in the box's buffer
        while time.monotonic() < deadline:
            self._check()
            tag = self._next_tag()
            self._write(f"PING #{tag}")
            until = min(deadline, time.monotonic() + _HANDSHAKE_PERIOD_S)
            while time.monotonic() < until:
                if self._ready.is_set():
                    self._handshake_done = True
                    return
                try:
                    reply = self._replies.get(timeout=0.01)
                except queue.Empty:
                    continue
                if reply.fields[0] == "PONG":
                    self._handshake_done = True
                    return
        raise DeviceTimeoutError(
            f"trigger box {self.port}: no PONG or READY in reply to 'PING' within {timeout_s:g} s"
        )

    def _simple(self, command: str, expect: str, *, idempotent: bool = True) -> list[str]:
        fields = self._command(command, idempotent=idempotent)[-1].fields
        if fields[0] != expect:
            raise ProtocolError(
                f"trigger box {self.port}: {command!r} got unexpected reply {' '.join(fields)!r}"
            )
        return fields

    def _int_field(self, command: str, fields: list[str], i: int) -> int:
        try:
            return int(fields[i])
        except (IndexError, ValueError):
            raise ProtocolError(
                f"trigger box {self.port}: {command!r} reply {' '.join(fields)!r} lacks integer field {i}"
            ) from None
