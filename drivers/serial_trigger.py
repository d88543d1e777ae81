"""Host driver for the trigger box (protocol: docs/trigger-protocol.md), over USB serial or raw HID.

`SerialTrigger` runs over a small byte `Transport` (`drivers.trigger_link`): pyserial for
CDC-ACM / UART boxes (`/dev/ttyACM0`, `serial:///dev/ttyACM0`), hidapi for boxes that enumerate
as HID (`hid://VID:PID[/SERIAL]`). Everything above the transport is shared, so both links pass
the same protocol tests.

The receive side runs on an acquisition thread from open to close; the line layer
(`drivers.trigger_lines.BoxLines`: checksums, tagged commands, the handshake) routes pulse
records to the pulse queue and replies to the command waiting for them. Here: the trigger's run
semantics. Pulse records lost to line noise show up as index gaps and are fetched again with
`TS?`; those that cannot be recovered stay visible as missing indices and counters.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import numpy as np

from drivers.base import Capability, Trigger
from drivers.lifecycle import Acquisition, DeliveryQueue
from drivers.registry import DeviceSpec
from drivers.trigger_lines import BoxLines
from drivers.trigger_link import (
    DEFAULT_BAUD,
    SerialTransport,
    Transport,
    open_hid_transport,
    parse_hid_address,
)
from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.errors import ConfigError, DeviceTimeoutError, ProtocolError
from rigd.core.host_clock import MONOTONIC, HostClock
from rigd.core.settings import TriggerSettings

log = logging.getLogger(__name__)

#: Most records one `TS?` may ask for (box limit).
TS_MAX_COUNT = 64
_READBACK_ATTEMPTS = 3
#: Pulse records waiting for read_pulses; one lost to a full queue is fetched again with `TS?`.
_PULSE_QUEUE = 1 << 20


class SerialTrigger(BoxLines, Trigger):
    """A trigger box speaking the line protocol; its clock is the rig timebase.

    `port` opens a serial port; pass `transport` instead for any other link (HID). The name
    says "serial" for the line protocol, which is the same whatever carries its bytes.
    `host_clock` stamps the pulse records' arrival (`host_time_ns`): the monotonic clock on
    hardware, a simulated world's own clock on a simulated box (`rigd.core.host_clock`).
    """

    _capabilities = frozenset({Capability.PULSE_TIMESTAMPS, Capability.PULSE_COUNT})

    def __init__(
        self,
        port: str | None = None,
        *,
        transport: Transport | None = None,
        baudrate: int = DEFAULT_BAUD,
        reply_timeout_s: float = 1.0,
        boot_timeout_s: float = 5.0,
        spec: str | None = None,
        on_close: Callable[[], None] | None = None,
        host_clock: HostClock = MONOTONIC,
    ) -> None:
        if (port is None) == (transport is None):
            raise ValueError("SerialTrigger needs exactly one of port and transport")
        super().__init__()
        if transport is None:
            assert port is not None
            transport = SerialTransport(port, baudrate=baudrate)
        self._open_lines(transport, reply_timeout_s, host_clock)
        self._label = f"trigger box {self.port}"
        self._spec = spec or self.port
        self._on_close = on_close
        self._stats_lock = threading.Lock()
        self._stats: dict[str, int] = {
            "lines": 0,
            "corrupt_lines": 0,
            "garbage_bytes": 0,
            "bad_records": 0,
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
        # The receive side runs from open to close: the handshake needs it already.
        self._rx_thread: Acquisition[tuple[int, int, int]] = Acquisition(
            self._label, self._grab, DeliveryQueue(_PULSE_QUEUE)
        )
        self._rx_thread.start()
        try:
            self._handshake(boot_timeout_s)
            ident = self._command("ID?", idempotent=True)[-1].fields
            if ident[0] != "ID" or len(ident) < 5:
                raise ProtocolError(f"trigger box {self.port}: malformed ID reply {' '.join(ident)!r}")
            self._info = DeviceInfo(
                kind="trigger",
                spec=self._spec,
                vendor=ident[1],
                model=ident[2],
                serial=ident[3],
                firmware=ident[4],
            )
        except BaseException:
            self._closed = True
            self._do_close()
            raise
        log.info(
            "trigger box %s: %s %s fw %s", self.port, self._info.vendor, self._info.model, self._info.firmware
        )

    def _check(self) -> None:
        self._check_open()

    # ------------------------------------------------------------------ Trigger hooks
    @property
    def stats(self) -> dict[str, int]:
        """Line and pulse counters since open (corrupt lines, recovered pulses, ...)."""
        with self._stats_lock:
            return dict(self._stats)

    def link_stats(self) -> dict[str, int]:
        return self.stats

    @property
    def missing_indices(self) -> list[int]:
        """Pulse indices of the current run that could not be recovered."""
        with self._stats_lock:
            return list(self._missing)

    def _do_configure(self, settings: TriggerSettings) -> None:
        rate = f"{settings.rate_hz:.6f}".rstrip("0").rstrip(".")
        self._simple(f"RATE {rate}", "OK")
        self._simple(f"WIDTH {settings.pulse_width_us}", "OK")

    def _do_arm(self) -> None:
        self._simple("ARM", "OK")
        self._reset_run()

    def _reset_run(self) -> None:
        self._rx_thread.queue.drain()
        with self._stats_lock:
            self._next_index = 0
            self._final_count = None
            self._missing = []

    def _do_start(self, n_pulses: int | None) -> int:
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

    def _do_stop(self) -> int:
        fields = self._simple("STOP", "OK")
        count = self._int_field("STOP", fields, 2)
        with self._stats_lock:
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

    def diag(self) -> dict[str, int]:
        """The box's own counters (`DIAG?`, protocol v1.1): records it could not send live,
        input bytes it lost, edges it armed late. A v1 box answers `ERR UNKNOWN`."""
        fields = self._simple("DIAG?", "DIAG")
        out: dict[str, int] = {}
        for f in fields[1:]:
            key, _, value = f.partition("=")
            if not value.isdigit():
                raise ProtocolError(f"trigger box {self.port}: DIAG? field {f!r} is not key=<count>")
            out[key] = int(value)
        return out

    def _is_running(self) -> bool:
        status = self._status()
        running = status["state"] == "RUNNING"
        if not running and int(status.get("t0", "-1")) >= 0:
            # The run is over, so every pulse record precedes this reply in the stream.
            with self._stats_lock:
                self._final_count = int(status["count"])
        return running

    def _pulse_count(self) -> int:
        return self._int_field("COUNT?", self._simple("COUNT?", "COUNT"), 1)

    def _clock_us(self) -> int:
        return self._int_field("CLOCK?", self._simple("CLOCK?", "CLOCK"), 1)

    def _read_pulses(self, timeout_s: float) -> PulseBatch:
        # Block for the first record only: callers loop on this, it must not spin.
        got = {i: (t, h) for i, t, h in self._rx_thread.queue.get(timeout_s, max_items=None)}
        with self._stats_lock:
            start = self._next_index
            final = self._final_count
        dupes = [i for i in got if i < start]
        for i in dupes:
            del got[i]
        if dupes:
            log.warning("trigger box %s: duplicate pulse records %s", self.port, dupes[:10])
            with self._stats_lock:
                self._stats["duplicate_pulses"] += len(dupes)
        end = max(got) + 1 if got else start
        if final is not None:
            end = max(end, final)
        missing = [i for i in range(start, end) if i not in got]
        if missing:
            self._recover(missing, got)
        with self._stats_lock:
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
                now = self.host_clock.now_ns()
                for r in replies[:-1]:
                    k = self._int_field("TS?", r.fields, 1)
                    if first <= k < first + count and k not in got:
                        got[k] = (self._int_field("TS?", r.fields, 2), now)
            want = [i for i in want if i not in got]
        recovered = len(missing) - len(want)
        with self._stats_lock:
            self._stats["recovered_pulses"] += recovered
            self._stats["unrecovered_pulses"] += len(want)
            self._missing.extend(want)
        if want:
            log.error("trigger box %s: %d pulse record(s) lost for good: %s", self.port, len(want), want[:20])

    def _stop_for_close(self) -> None:
        # No STOP before the handshake, nor to a box whose link is gone.
        if self._handshake_done and self._rx_thread.error is None:
            super()._stop_for_close()

    def _do_close(self) -> None:
        self._rx_thread.stop()
        try:
            self._transport.close()
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


def open_hid_trigger(spec: DeviceSpec) -> SerialTrigger:
    """`hid://16c0:0486` or `hid://16c0:0486/SERIAL?reply_timeout_s=1&boot_timeout_s=5`."""
    spec.check_params({"reply_timeout_s", "boot_timeout_s"})
    vid, pid, serial_nbr = parse_hid_address(spec)
    transport = open_hid_transport(vid, pid, serial_nbr)
    try:
        return SerialTrigger(
            transport=transport,
            reply_timeout_s=spec.float_param("reply_timeout_s", 1.0),
            boot_timeout_s=spec.float_param("boot_timeout_s", 5.0),
            spec=spec.raw,
        )
    except BaseException:
        transport.close()
        raise


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
