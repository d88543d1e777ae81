"""`file://PATH.raw` (or `.dat`) replay as an event sensor.

The file is decoded by the production EVT decoder in chunks of constant size. Replay runs as
fast as the reader asks (`pace=0`) or paced against the host clock (`pace=1` is real time,
`pace=0.5` half speed). With `loop=1` the recording starts over at its end, each pass shifted
by the recording's span plus one microsecond so time keeps increasing.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from drivers.base import Capability, EventSensor
from drivers.evt import JUMP_CONFIRM, Decoded, RawReader, read_dat, warm_up_decoder
from drivers.registry import DeviceSpec
from rigd.core.devices import DeviceInfo
from rigd.core.errors import ConfigError, EventDataError
from rigd.core.events import EventPacket, TriggerEvents
from rigd.core.settings import EventSensorSettings

log = logging.getLogger(__name__)


class FileEventSensor(EventSensor):
    """Replays a RAW or DAT recording through the EventSensor interface, on the reader's
    thread: the reader sets the pace (`pace=0`), so nothing is ever dropped."""

    def __init__(
        self,
        path: str | Path,
        *,
        pace: float = 0.0,
        loop: bool = False,
        chunk_bytes: int = 1 << 20,
        strict: bool = False,
        jump_confirm: int = JUMP_CONFIRM,
        spec: str = "",
    ) -> None:
        super().__init__(EventSensorSettings(enable_trigger_in=False))
        self.path = Path(path)
        if self.path.is_dir():
            raise ConfigError(f"event file {self.path} is a directory, not a RAW or DAT recording")
        if not self.path.is_file():
            raise ConfigError(f"event file {self.path} does not exist")
        if pace < 0 or not np.isfinite(pace):
            raise ConfigError(f"event file {self.path}: pace must be >= 0, got {pace}")
        self.pace, self.loop, self.chunk_bytes, self.strict = pace, loop, chunk_bytes, strict
        self.jump_confirm = jump_confirm
        self._label = f"event file sensor {self.path}"
        self._is_dat = self.path.suffix.lower() == ".dat"
        self._dat_skipped: dict[str, int] = {}
        try:
            self._read_header(strict)
        except (EventDataError, OSError) as exc:
            raise ConfigError(f"event file {self.path}: {_reason(exc, self.path)}") from exc
        fields = self.header_fields
        self._info = DeviceInfo(
            kind="event_sensor",
            spec=spec or f"file://{self.path}",
            vendor="file",
            model=fields.get("camera_integrator_name", "") + " " + fields.get("plugin_name", ""),
            serial=self._serial,
            firmware=f"format={self._fmt}",
            facts={"evt_format": self._fmt, **{f"header.{k}": v for k, v in fields.items()}},
        )
        self._has_triggers: bool | None = None
        self._chunks: Iterator[Decoded] | None = None
        self._reader: RawReader | None = None
        self._pending = Decoded.empty()
        self._shift = 0
        self._span = 0
        self._first_t: int | None = None
        self._t0_host = 0.0
        self._passes = 0

    def _read_header(self, strict: bool) -> None:
        """Format, geometry, serial and header fields; an empty or unreadable file raises."""
        if self.path.stat().st_size == 0:
            raise EventDataError("empty file, not a recording")
        if self._is_dat:
            hdr, ev = read_dat(self.path, strict=strict)
            if hdr.width and hdr.height:
                self._geometry = (hdr.width, hdr.height)
            elif len(ev):  # old DAT files carry no geometry: the smallest that holds the data
                self._geometry = (int(ev.x.max()) + 1, int(ev.y.max()) + 1)
            else:
                raise ConfigError(f"event file {self.path}: no geometry in the header and no events")
            self._fmt, serial, fields = "dat", "", dict(hdr.fields)
        else:
            # checks the header (and jump_confirm)
            with RawReader(
                self.path, self.chunk_bytes, strict=strict, jump_confirm=self.jump_confirm
            ) as reader:
                raw_hdr = reader.header
            self._geometry = (raw_hdr.width, raw_hdr.height)
            self._fmt, serial, fields = raw_hdr.fmt, raw_hdr.serial_number or "", raw_hdr.fields
        self.header_fields = fields
        self._serial = serial

    @property
    def capabilities(self) -> frozenset[Capability]:
        """DEVICE_TIMESTAMPS; TRIGGER_IN only when the recording holds trigger edges to replay."""
        if self._has_triggers is None:
            self._has_triggers = self._scan_for_triggers()
        if self._has_triggers:
            return frozenset({Capability.DEVICE_TIMESTAMPS, Capability.TRIGGER_IN})
        return frozenset({Capability.DEVICE_TIMESTAMPS})

    def _scan_for_triggers(self) -> bool:
        """Decode until the first trigger edge (DAT files hold none); once, on first asking."""
        if self._is_dat:
            return False
        with RawReader(self.path, self.chunk_bytes, strict=False, jump_confirm=self.jump_confirm) as reader:
            found = any(len(chunk.triggers) for chunk in reader)
        log.debug("%s: trigger edges in the recording: %s", self.label, found)
        return found

    @property
    def geometry(self) -> tuple[int, int]:
        return self._geometry

    @property
    def evt_format(self) -> str:
        return self._fmt

    def warm_up(self) -> None:
        """The RAW decoder of the file's format (a DAT file is read by numpy alone)."""
        if not self._is_dat:
            warm_up_decoder(self._fmt, *self._geometry)

    def _do_start(self) -> None:
        self._open_pass()
        self._t0_host = time.monotonic()

    def _do_stop(self) -> None:
        self._close_reader()

    def _do_close(self) -> None:
        self._close_reader()

    def _counters(self) -> tuple[int, dict[str, int]]:
        extra = {"passes": self._passes}
        if self._reader is not None:
            extra.update({f"decoder_skipped_{k}": v for k, v in self._reader.stats.items()})
            if self._reader.decoder.skipped_offsets:
                extra["decoder_first_skipped_offset"] = self._reader.decoder.skipped_offsets[0]
            extra.update({f"decoder_{k}": v for k, v in self._reader.decoder.jump_stats.items()})
        extra.update({f"decoder_skipped_{k}": v for k, v in self._dat_skipped.items()})
        return 0, extra

    # -- replay ---------------------------------------------------------------------------
    def _open_pass(self) -> None:
        self._close_reader()
        self._passes += 1
        if self._is_dat:
            hdr, ev = read_dat(self.path, strict=self.strict)
            self._dat_skipped = hdr.skipped
            self._chunks = iter([Decoded(ev, TriggerEvents.empty())])
        else:
            self._reader = RawReader(
                self.path, self.chunk_bytes, strict=self.strict, jump_confirm=self.jump_confirm
            )
            self._chunks = iter(self._reader)

    def _close_reader(self) -> None:
        if self._reader is not None:
            self._reader.close()
        self._reader, self._chunks = None, None

    def _next_chunk(self) -> bool:
        """Append the next decoded chunk to the pending buffer; False at the very end."""
        while True:
            if self._chunks is None:
                return False
            chunk = next(self._chunks, None)
            if chunk is None:
                if not self.loop or self._first_t is None:
                    return False
                self._shift += self._span + 1
                self._open_pass()
                continue
            ev, tr = chunk.events, chunk.triggers
            if len(ev) == 0 and len(tr) == 0:
                continue
            if self._first_t is None:
                self._first_t = _first_time(chunk)
            last = max(int(a[-1]) for a in (ev.t, tr.t) if len(a))
            if self._passes == 1:
                self._span = max(self._span, last - self._first_t)
            if self._shift:
                ev = ev.with_time(ev.t + self._shift)
                tr = TriggerEvents(tr.t + self._shift, tr.p, tr.channel)
            self._pending = Decoded.concatenate([self._pending, Decoded(ev, tr)])
            return True

    def _read(self, timeout_s: float) -> EventPacket | None:
        if self._chunks is None and not len(self._pending.events) and not len(self._pending.triggers):
            return None
        deadline = time.monotonic() + max(0.0, timeout_s)
        while True:
            if not len(self._pending.events) and not len(self._pending.triggers) and not self._next_chunk():
                return None
            if self.pace == 0 or self._first_t is None:
                out, self._pending = self._pending, Decoded.empty()
                return _packet(out)
            due = self._first_t + int((time.monotonic() - self._t0_host) * 1e6 * self.pace)
            out, rest = _split(self._pending, due)
            if len(out.events) or len(out.triggers):
                self._pending = rest
                return _packet(out)
            t_next = _first_time(rest)
            wait = (t_next - due) / 1e6 / self.pace
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            time.sleep(max(0.0, min(wait, left)))


def _reason(exc: EventDataError | OSError, path: Path) -> str:
    """The problem without the path that the message already leads with (one line)."""
    if isinstance(exc, OSError):
        return f"cannot read: {exc.strerror or exc}"
    return str(exc).removeprefix(f"{path}: ")


def _packet(d: Decoded) -> EventPacket:
    return EventPacket(d.events, d.triggers, time.monotonic_ns())


def _first_time(d: Decoded) -> int:
    return min(int(a[0]) for a in (d.events.t, d.triggers.t) if len(a))


def _split(d: Decoded, t_due: int) -> tuple[Decoded, Decoded]:
    """Events and triggers with t <= t_due, and the rest."""
    ie = int(np.searchsorted(d.events.t, t_due, side="right"))
    it = int(np.searchsorted(d.triggers.t, t_due, side="right"))
    return (
        Decoded(d.events[:ie], d.triggers[:it]),
        Decoded(d.events[ie:], d.triggers[it:]),
    )


def open_file_event_sensor(spec: DeviceSpec) -> FileEventSensor:
    """Factory for `file:///abs/path.raw?pace=1&loop=1&strict=0&jump_confirm=2` (also `.dat`)."""
    spec.check_params({"pace", "loop", "strict", "chunk_bytes", "jump_confirm"})
    path = (spec.location + spec.path) if spec.location else spec.path
    if not path:
        raise ConfigError(f"device spec {spec.raw!r}: no file path")
    return FileEventSensor(
        path,
        pace=spec.float_param("pace", 0.0),
        loop=bool(spec.int_param("loop", 0)),
        strict=bool(spec.int_param("strict", 0)),
        chunk_bytes=spec.int_param("chunk_bytes", 1 << 20),
        jump_confirm=spec.int_param("jump_confirm", JUMP_CONFIRM),
        spec=spec.raw,
    )
