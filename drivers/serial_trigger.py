"""Host driver for the serial trigger box (protocol: docs/trigger-protocol.md).

A reader thread owns the receive side: it splits lines, verifies the `*HH` checksum, sends
async pulse records (`P <index> <t_us>`) to a pulse queue stamped with the host monotonic
clock on reception, and everything else to a reply queue. Commands are serialized by a
lock and tagged (`#n`) so a late reply to an earlier command can never be taken for the
current one. Pulse records lost to line noise show up as index gaps and are fetched again
with `TS?`; those that cannot be recovered stay visible as missing indices and counters.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import serial

from drivers.base import Capability, DeviceInfo, PulseBatch, Trigger, TriggerSettings
from drivers.registry import DeviceSpec
from rigd.core.errors import ConfigError, DeviceError, DeviceTimeoutError, ProtocolError

log = logging.getLogger(__name__)

DEFAULT_BAUD = 115_200
#: Most records one `TS?` may ask for (box limit).
TS_MAX_COUNT = 64
_READBACK_ATTEMPTS = 3
#: After a corrupt line arrives during a command, how long to wait for a good reply before retrying.
_CORRUPT_GRACE_S = 0.15
_HANDSHAKE_PERIOD_S = 0.1


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


class SerialTrigger(Trigger):
    """A trigger box on a serial port; its clock is the rig timebase."""

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = DEFAULT_BAUD,
        reply_timeout_s: float = 1.0,
        boot_timeout_s: float = 5.0,
        spec: str | None = None,
        on_close: Callable[[], None] | None = None,
    ) -> None:
        self.port = port
        self.reply_timeout_s = reply_timeout_s
        self._spec = spec or port
        self._on_close = on_close
        self._closed = False
        self._cmd_lock = threading.Lock()
        self._state_lock = threading.Lock()
        self._replies: queue.Queue[_Reply] = queue.Queue()
        self._pulses: queue.Queue[tuple[int, int, int]] = queue.Queue()
        self._reader_error: BaseException | None = None
        self._stop_reader = threading.Event()
        self._corrupt_seen = 0  # bumps on every corrupt line; waiters compare before/after
        self._ready = threading.Event()
        self._handshake_done = False
        self._tag = 0
        self._stats: dict[str, int] = {
            "lines": 0,
            "corrupt_lines": 0,
            "garbage_bytes": 0,
            "pulses_received": 0,
            "recovered_pulses": 0,
            "unrecovered_pulses": 0,
            "duplicate_pulses": 0,
            "stale_replies": 0,
            "retries": 0,
        }
        # Per-run pulse bookkeeping (reset by ARM).
        self._next_index = 0
        self._final_count: int | None = None
        self._missing: list[int] = []
        self._settings = TriggerSettings()
        try:
            self._ser = serial.serial_for_url(port, baudrate=baudrate, timeout=0.05, write_timeout=1.0)
        except (serial.SerialException, ValueError, OSError) as exc:
            raise DeviceError(f"cannot open trigger box port {port!r}: {exc}") from exc
        self._reader = threading.Thread(target=self._read_loop, name=f"trigger-rx-{port}", daemon=True)
        self._reader.start()
        try:
            self._handshake(boot_timeout_s)
            ident = self._command("ID?", idempotent=True)[-1].fields
            if ident[0] != "ID" or len(ident) < 5:
                raise ProtocolError(f"trigger box {port}: malformed ID reply {' '.join(ident)!r}")
            self._info = DeviceInfo(
                kind="trigger",
                spec=self._spec,
                vendor=ident[1],
                model=ident[2],
                serial=ident[3],
                firmware=ident[4],
            )
        except BaseException:
            self._shutdown(send_stop=False)
            raise
        log.info(
            "trigger box %s: %s %s fw %s", port, self._info.vendor, self._info.model, self._info.firmware
        )

    # ------------------------------------------------------------------ reader
    def _read_loop(self) -> None:
        buf = bytearray()
        while not self._stop_reader.is_set():
            try:
                chunk = self._ser.read(max(1, self._ser.in_waiting))
            except (serial.SerialException, OSError, TypeError) as exc:
                # TypeError: pyserial on a port closed under it; only benign while closing.
                if self._stop_reader.is_set():
                    log.debug("trigger box %s: reader ends on close: %s", self.port, exc)
                    return
                log.error("trigger box %s: serial read failed: %s", self.port, exc)
                self._reader_error = exc
                return
            if not chunk:
                continue
            buf.extend(chunk)
            while True:
                nl = buf.find(b"\n")
                if nl < 0:
                    break
                line = bytes(buf[:nl])
                del buf[: nl + 1]
                try:
                    self._handle_line(line)
                except Exception as exc:
                    log.exception("trigger box %s: cannot handle line %r", self.port, line)
                    self._reader_error = exc
            if len(buf) > 4096:  # no newline in 4 KiB: noise, not a protocol line
                with self._state_lock:
                    self._stats["garbage_bytes"] += len(buf)
                    self._stats["corrupt_lines"] += 1
                    self._corrupt_seen += 1
                buf.clear()

    def _corrupt(self, line: bytes, why: str) -> None:
        log.warning("trigger box %s: dropped corrupt line (%s): %r", self.port, why, line)
        with self._state_lock:
            self._stats["corrupt_lines"] += 1
            self._corrupt_seen += 1

    def _handle_line(self, raw: bytes) -> None:
        host_ns = time.monotonic_ns()
        if raw.endswith(b"\r"):
            raw = raw[:-1]
        if not raw:
            return
        start = raw.rfind(b"$")
        if start < 0:
            self._corrupt(raw, "no '$' start")
            return
        if start:
            with self._state_lock:
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
        with self._state_lock:
            self._stats["lines"] += 1
        kind = fields[0]
        if kind == "P":
            if len(fields) != 3:
                raise ProtocolError(f"trigger box {self.port}: malformed pulse record {raw!r}")
            with self._state_lock:
                self._stats["pulses_received"] += 1
            self._pulses.put((int(fields[1]), int(fields[2]), host_ns))
        elif kind == "END":
            with self._state_lock:
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
    def _check(self) -> None:
        if self._closed:
            raise DeviceError(f"trigger box {self.port} is closed")
        err = self._reader_error
        if err is not None:
            raise ProtocolError(f"trigger box {self.port}: receive side failed: {err}") from err

    def _write(self, payload: str) -> None:
        try:
            self._ser.write(_frame_command(payload))
        except (serial.SerialException, OSError) as exc:
            raise DeviceError(f"trigger box {self.port}: writing {payload!r} failed: {exc}") from exc

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
            with self._state_lock:
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
                with self._state_lock:
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
                with self._state_lock:
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

    # ------------------------------------------------------------------ Trigger API
    @property
    def info(self) -> DeviceInfo:
        return self._info

    @property
    def capabilities(self) -> frozenset[Capability]:
        return frozenset({Capability.PULSE_TIMESTAMPS, Capability.PULSE_COUNT})

    @property
    def stats(self) -> dict[str, int]:
        """Line and pulse counters since open (corrupt lines, recovered pulses, ...)."""
        with self._state_lock:
            return dict(self._stats)

    def link_stats(self) -> dict[str, int]:
        return self.stats

    @property
    def missing_indices(self) -> list[int]:
        """Pulse indices of the current run that could not be recovered."""
        with self._state_lock:
            return list(self._missing)

    def configure(self, settings: TriggerSettings) -> None:
        period_us = 1e6 / settings.rate_hz
        if settings.pulse_width_us >= period_us:
            raise ConfigError(
                f"trigger {self.port}: pulse width {settings.pulse_width_us} us must be shorter "
                f"than the period {period_us:.1f} us at {settings.rate_hz:g} Hz"
            )
        rate = f"{settings.rate_hz:.6f}".rstrip("0").rstrip(".")
        self._simple(f"RATE {rate}", "OK")
        self._simple(f"WIDTH {settings.pulse_width_us}", "OK")
        self._settings = settings

    def arm(self) -> None:
        self._simple("ARM", "OK")
        self._reset_run()

    def _reset_run(self) -> None:
        while True:
            try:
                self._pulses.get_nowait()
            except queue.Empty:
                break
        with self._state_lock:
            self._next_index = 0
            self._final_count = None
            self._missing = []

    def start(self, n_pulses: int | None = None) -> int:
        if n_pulses is not None and n_pulses < 1:
            raise ConfigError(f"trigger {self.port}: n_pulses must be >= 1, got {n_pulses}")
        command = "START" if n_pulses is None else f"START {n_pulses}"
        try:
            fields = self._simple(command, "OK", idempotent=False)
        except DeviceTimeoutError:
            # The reply may have been lost to noise: STATUS? tells whether START took.
            status = self._status()
            t0 = int(status.get("t0", "-1"))
            if t0 < 0:
                raise
            log.warning("trigger box %s: START reply lost; box reports t0=%d", self.port, t0)
            return t0
        return self._int_field(command, fields, 2)

    def stop(self) -> int:
        fields = self._simple("STOP", "OK")
        count = self._int_field("STOP", fields, 2)
        with self._state_lock:
            self._final_count = count
        return count

    def _status(self) -> dict[str, str]:
        fields = self._simple("STATUS?", "STATUS")
        out = {"state": fields[1] if len(fields) > 1 else "?"}
        for f in fields[2:]:
            key, _, value = f.partition("=")
            out[key] = value
        return out

    def status(self) -> dict[str, str]:
        """The box's state, counters and settings as it reports them."""
        return self._status()

    def is_running(self) -> bool:
        status = self._status()
        running = status["state"] == "RUNNING"
        if not running and int(status.get("t0", "-1")) >= 0:
            # The run is over, so every pulse record precedes this reply in the stream.
            with self._state_lock:
                self._final_count = int(status["count"])
        return running

    def pulse_count(self) -> int:
        return self._int_field("COUNT?", self._simple("COUNT?", "COUNT"), 1)

    def clock_us(self) -> int:
        return self._int_field("CLOCK?", self._simple("CLOCK?", "CLOCK"), 1)

    def read_pulses(self, timeout_s: float) -> PulseBatch:
        self._check()
        got: dict[int, tuple[int, int]] = {}
        try:  # block for the first record only: callers loop on this, it must not spin
            i, t, h = self._pulses.get(timeout=max(0.0, timeout_s))
            got[i] = (t, h)
        except queue.Empty:
            pass
        while True:
            try:
                i, t, h = self._pulses.get_nowait()
            except queue.Empty:
                break
            got[i] = (t, h)
        with self._state_lock:
            start = self._next_index
            final = self._final_count
        dupes = [i for i in got if i < start]
        for i in dupes:
            del got[i]
        if dupes:
            log.warning("trigger box %s: duplicate pulse records %s", self.port, dupes[:10])
            with self._state_lock:
                self._stats["duplicate_pulses"] += len(dupes)
        end = max(got) + 1 if got else start
        if final is not None:
            end = max(end, final)
        missing = [i for i in range(start, end) if i not in got]
        if missing:
            self._recover(missing, got)
        with self._state_lock:
            self._next_index = end
        idx = np.array(sorted(got), dtype=np.int64)
        t_us = np.array([got[i][0] for i in idx], dtype=np.int64)
        host = np.array([got[i][1] for i in idx], dtype=np.int64)
        return PulseBatch(idx, t_us, host)

    def _recover(self, missing: list[int], got: dict[int, tuple[int, int]]) -> None:
        """Fetch lost pulse records with TS?; record the ones that stay lost."""
        log.info(
            "trigger box %s: recovering %d lost pulse record(s) from %d", self.port, len(missing), missing[0]
        )
        want = list(missing)
        for _ in range(_READBACK_ATTEMPTS):
            if not want:
                break
            for first, count in _ranges(want, TS_MAX_COUNT):
                try:
                    replies = self._command(f"TS? {first} {count}", idempotent=True)
                except DeviceTimeoutError as exc:
                    log.warning(
                        "trigger box %s: readback of %d..%d failed: %s", self.port, first, first + count, exc
                    )
                    continue
                now = time.monotonic_ns()
                for r in replies[:-1]:
                    k = self._int_field("TS?", r.fields, 1)
                    if first <= k < first + count and k not in got:
                        got[k] = (self._int_field("TS?", r.fields, 2), now)
            want = [i for i in want if i not in got]
        recovered = len(missing) - len(want)
        with self._state_lock:
            self._stats["recovered_pulses"] += recovered
            self._stats["unrecovered_pulses"] += len(want)
            self._missing.extend(want)
        if want:
            log.error("trigger box %s: %d pulse record(s) lost for good: %s", self.port, len(want), want[:20])

    def close(self) -> None:
        """Stop pulsing (best effort), end the reader, close the port. Idempotent."""
        if self._closed:
            return
        self._shutdown(send_stop=self._reader_error is None)

    def _shutdown(self, *, send_stop: bool) -> None:
        if send_stop and self._handshake_done:
            try:
                self.stop()
            except DeviceError as exc:
                log.warning("trigger box %s: STOP on close failed: %s", self.port, exc)
        self._closed = True
        self._stop_reader.set()
        self._reader.join()
        try:
            self._ser.close()
        finally:
            if self._on_close is not None:
                on_close, self._on_close = self._on_close, None
                on_close()


def _ranges(indices: list[int], max_len: int) -> list[tuple[int, int]]:
    """Contiguous (first, count) runs of sorted indices, each at most max_len long."""
    out: list[tuple[int, int]] = []
    for i in sorted(indices):
        if out and out[-1][0] + out[-1][1] == i and out[-1][1] < max_len:
            out[-1] = (out[-1][0], out[-1][1] + 1)
        else:
            out.append((i, 1))
    return out


def open_serial_trigger(spec: DeviceSpec) -> SerialTrigger:
    """`/dev/ttyACM0`, `COM3` or `serial:///dev/ttyACM0?baud=115200&reply_timeout_s=1`."""
    spec.check_params({"baud", "reply_timeout_s", "boot_timeout_s"})
    port = spec.path or spec.location
    if spec.location and spec.path:  # serial://host/path is not a port name we know
        raise ConfigError(f"device spec {spec.raw!r}: use serial:///dev/PORT (three slashes) or a bare path")
    if not port:
        raise ConfigError(f"device spec {spec.raw!r} names no serial port")
    return SerialTrigger(
        port,
        baudrate=spec.int_param("baud", DEFAULT_BAUD),
        reply_timeout_s=spec.float_param("reply_timeout_s", 1.0),
        boot_timeout_s=spec.float_param("boot_timeout_s", 5.0),
        spec=spec.raw,
    )
