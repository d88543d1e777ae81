"""`file://PATH.raw` (or `.dat`) replay as an event sensor.

EVT 3.0 and EVT 2.0 recordings replay as a device sends them: the file's stream is read into
memory once at start (`drivers.evt_file_stream`), each read hands out the bytes that are due,
cut at word boundaries where the stream's time words say everything before the cut is due, and
a `StreamDecoder` decodes them on the reader's thread, as a Prophesee camera's bytes are. Every
packet carries the bytes it was decoded from (`EventPacket.raw`, an `EvtChunk`), so a take can
store the stream as sent. Replay runs as fast as the reader asks (`pace=0`, `chunk_bytes` per
read) or paced against the host clock (`pace=1` is real time, `pace=0.5` half speed), at most
one buffer per `packet_us` of stream time; `burst=START_S:LEN_S:PACE` switches to PACE for
LEN_S seconds of host time from START_S on (a load peak inside a steady take).

`loop=1` (EVT 3.0) repeats the recording's whole TIME_HIGH periods (4096 us) from its first
period start, each pass's TIME_HIGH words moved on by the periods before it (see
`drivers.evt_file_stream`): the stream stays valid and keeps the recording's density; what it
keeps of the recording is in `stats().extra` (`loop_us`, `recorded_us`; the Gen4.1 sample
keeps 8192 of the 8811 us its time words span, its last, partial period dropped). A looped
stream's clock runs in real time at any pace up to 1, as a device's does: `pace=0.8` puts quiet
TIME_HIGH periods between passes (one in every ~10 of stream time for the Gen4.1 sample, 2.5
periods a pass on average) so that the events come at 0.8 x the recording's rate; above 1 the
clock runs faster (the recording has no more events per microsecond to give).

EVT 2.1 recordings, EVT 2.0 with `loop=1` and DAT files (decoded events, no wire bytes at all)
keep the older replay: the file is decoded in chunks of `chunk_bytes` and handed out decoded
(`raw` None), a looped pass shifted by the recording's span plus one microsecond.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from drivers.base import Capability, EventSensor
from drivers.evt_file_stream import EvtFileStream, Pace
from drivers.registry import DeviceSpec
from rigd.core.devices import DeviceInfo
from rigd.core.errors import ConfigError, EventDataError
from rigd.core.events import EventPacket, EvtChunk, TriggerEvents
from rigd.core.settings import EventSensorSettings
from rigd.evt import JUMP_CONFIRM, Decoded, RawReader, Scanned, StreamDecoder, read_dat, warm_up_decoder

log = logging.getLogger(__name__)


class FileEventSensor(EventSensor):
    """Replays a RAW or DAT recording through the EventSensor interface, on the reader's
    thread: the reader sets the pace (`pace=0`), so nothing is ever dropped. Not a
    `drivers.evt_stream.DecodingEventSensor`: a file has no device to poll, and its stream is
    cut by due time where it is read, so no acquisition thread or queue stands between them."""

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
        packet_us: int = 1000,
        burst: tuple[float, float, float] | None = None,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        super().__init__(EventSensorSettings(enable_trigger_in=False))
        self.path = Path(path)
        if self.path.is_dir():
            raise ConfigError(f"event file {self.path} is a directory, not a RAW or DAT recording")
        if not self.path.is_file():
            raise ConfigError(f"event file {self.path} does not exist")
        if pace < 0 or not np.isfinite(pace):
            raise ConfigError(f"event file {self.path}: pace must be >= 0, got {pace}")
        if chunk_bytes < 1 or packet_us < 1:
            raise ConfigError(
                f"event file {self.path}: chunk_bytes ({chunk_bytes}) and packet_us ({packet_us}) "
                "must be >= 1"
            )
        self.pace, self.loop, self.chunk_bytes, self.strict = pace, loop, chunk_bytes, strict
        self.jump_confirm = jump_confirm
        self.packet_us = packet_us
        self._pace = Pace(pace, *(burst or (0.0, 0.0, 0.0)), real_clock=loop)
        self._clock, self._sleep = clock, sleep
        self._header_size = 0
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
        # wire-byte replay (EVT 3.0, EVT 2.0 without loop): see `_read_wire`
        self.wire = not self._is_dat and (self._fmt == "evt3" or (self._fmt == "evt2" and not loop))
        self.delivers_evt_words = self.wire
        self._stream: EvtFileStream | None = None
        self._decoder: StreamDecoder | None = None
        self._stream_id = -1
        self._pos = 0  # stream bytes handed to the decoder
        self._chunk_at = 0  # where the next packet's EvtChunk starts, and the decoder state there
        self._chunk_state = np.empty(0, np.int64)
        self._stopped_s: float | None = None  # host time (s since start) the device stopped at
        self._ended = False
        self._bytes_delivered = 0

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
            self._header_size = raw_hdr.size
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

    @property
    def stream_time_us(self) -> int | None:
        """How far the decoded stream has got, its time words included (EVT 3.0 wire replay)."""
        return None if self._decoder is None else self._decoder.time_us

    def _do_start(self) -> None:
        if not self.wire:
            self._open_pass()
            self._t0_host = time.monotonic()
            return
        if self._stream is None:  # the file's bytes, read once: later starts replay them again
            try:
                self._stream = EvtFileStream(
                    self.path,
                    self._header_size,
                    self._fmt,
                    loop=self.loop,
                    pace=self._pace if self.loop else None,
                )
            except OSError as exc:
                raise ConfigError(f"event file {self.path}: {_reason(exc, self.path)}") from exc
        width, height = self._geometry
        self._decoder = StreamDecoder(
            self._fmt,
            width=width,
            height=height,
            strict=self.strict,
            offset=self._header_size,
            jump_confirm=self.jump_confirm,
        )
        self._stream_id += 1
        self._pos = self._chunk_at = 0
        self._chunk_state = self._decoder.state_copy()
        self._stopped_s, self._ended = None, False
        self._t0_host = self._clock()

    def _do_stop(self) -> None:
        if self.wire:
            self._stopped_s = self._clock() - self._t0_host
        self._close_reader()

    def _do_close(self) -> None:
        self._close_reader()

    def _counters(self) -> tuple[int, dict[str, int]]:
        if self.wire:
            return 0, self._wire_counters()
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
        if self.wire:
            return self._read_wire(timeout_s)
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

    # -- wire-byte replay (reader's thread) --------------------------------------------------
    def _due_us(self) -> int | None:
        """Stream time due now (us since the stream's start); None when unpaced and running."""
        if self._stopped_s is not None:  # a stopped device sent what was due when it stopped
            return self._pace.stream_us(self._stopped_s) if self._pace.paced else -1
        if not self._pace.paced:
            return None
        due = self._pace.stream_us(self._clock() - self._t0_host)
        return due // self.packet_us * self.packet_us  # one buffer per packet_us, as a device

    def _read_wire(self, timeout_s: float) -> EventPacket | None:
        """The bytes due now, decoded; waits up to `timeout_s` for some to become due."""
        stream, decoder = self._stream, self._decoder
        if stream is None or decoder is None or self._ended:
            return None
        deadline = self._clock() + max(0.0, timeout_s)
        ws = stream.word_bytes
        step = max(ws, self.chunk_bytes // ws * ws)
        while True:
            due = self._due_us()
            cut = self._pos + step
            if due is not None:
                cut = min(cut, stream.cut(due))
            end = stream.end
            if end is not None:
                cut = min(cut, end)
            if cut > self._pos:
                data = stream.read(self._pos, cut)
                start, self._pos = self._pos, cut
                packet = self._packet(decoder.scan(data), data, start, last=False)
                if packet is not None:
                    return packet
                continue
            if self._stopped_s is not None or (end is not None and self._pos >= end):
                self._ended = True  # held words decided now: no more bytes will tell
                tail = decoder.finish() if self._stopped_s is None else decoder.flush()
                return self._packet(Scanned.of(tail), b"", self._pos, last=True)
            now = self._clock()
            left = deadline - now
            if left <= 0:
                return None
            nxt = stream.next_due_us(self._pos)
            wait = left
            if nxt is not None:
                target = -(-nxt // self.packet_us) * self.packet_us
                wait = self._pace.host_s(target) - (now - self._t0_host)
            self._sleep(max(0.0, min(wait, left)))

    def _packet(self, scanned: Scanned, fed: bytes, fed_at: int, *, last: bool) -> EventPacket | None:
        """The packet of what the decoder consumed since the last packet; its EvtChunk holds
        exactly those bytes. None while nothing was decoded (the decoder holds the words back at
        a time jump, or they are time words alone): the next packet's chunk starts earlier.
        The `last` packet of a stream carries its remaining bytes, events or not."""
        assert self._stream is not None
        assert self._decoder is not None
        consumed = self._decoder.bytes_consumed
        if consumed <= self._chunk_at or (scanned.empty and not last):
            return None
        if fed_at == self._chunk_at and consumed == fed_at + len(fed):
            data = fed
        else:  # held words: the chunk starts before (or ends short of) what was fed
            data = self._stream.read(self._chunk_at, consumed)
        geometry = (self._decoder.width, self._decoder.height)
        raw = EvtChunk(self._fmt, data, self._chunk_state, self._stream_id, self._chunk_at, geometry=geometry)
        self._chunk_at, self._chunk_state = consumed, self._decoder.state_copy()
        self._bytes_delivered += len(data)
        return scanned.packet(self._arrival_ns(consumed), raw)

    def _arrival_ns(self, pos: int) -> int:
        """Host time (monotonic ns) the bytes before `pos` were in memory: when they became
        due (at a `packet_us` boundary), not when the reader got to them, as a device's buffer
        is stamped on arrival; now when unpaced."""
        now = time.monotonic_ns()
        if not self._pace.paced or self._stream is None:
            return now
        due = self._stream.due_at_us(pos)
        due = -(-due // self.packet_us) * self.packet_us
        host_s = self._t0_host + self._pace.host_s(due)
        if self._clock is not time.monotonic:  # an injected clock: its own time, unclamped
            return int(host_s * 1e9)
        return min(now, int(host_s * 1e9))

    def _wire_counters(self) -> dict[str, int]:
        extra = {"bytes_delivered": self._bytes_delivered, "passes": 0, "loop_us": 0, "recorded_us": 0}
        if self._stream is not None:
            extra["passes"] = self._stream.passes_at(self._pos) if self._stream_id >= 0 else 0
            extra["loop_us"] = self._stream.period_us
            extra["recorded_us"] = self._stream.recorded_us
            due = self._due_us()
            if due is not None and self._pace.paced and self._stream_id >= 0:
                # bytes a device would have sent by now (or by its stop) that were not read yet
                due_bytes = self._stream.cut(due)
                if self._stream.end is not None:
                    due_bytes = min(due_bytes, self._stream.end)
                extra["bytes_unread"] = max(0, due_bytes - self._pos)
        if self._decoder is not None:
            extra.update({f"decoder_skipped_{k}": v for k, v in self._decoder.stats.items()})
            if self._decoder.skipped_offsets:
                extra["decoder_first_skipped_offset"] = self._decoder.skipped_offsets[0]
            extra.update({f"decoder_{k}": v for k, v in self._decoder.jump_stats.items()})
        return extra


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
    """Factory for `file:///abs/path.raw?pace=1&loop=1&strict=0&jump_confirm=2&packet_us=1000
    &burst=START_S:LEN_S:PACE` (also `.dat`)."""
    spec.check_params({"pace", "loop", "strict", "chunk_bytes", "jump_confirm", "packet_us", "burst"})
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
        packet_us=spec.int_param("packet_us", 1000),
        burst=_burst(spec),
    )


def _burst(spec: DeviceSpec) -> tuple[float, float, float] | None:
    """`burst=START_S:LEN_S:PACE`, or None."""
    text = spec.params.get("burst")
    if text is None:
        return None
    try:
        start, length, pace = (float(v) for v in str(text).split(":"))
    except ValueError:
        raise ConfigError(
            f"device spec {spec.raw!r}: burst={text!r} is not START_S:LEN_S:PACE (three numbers)"
        ) from None
    return start, length, pace
