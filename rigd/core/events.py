"""Event arrays: struct-of-arrays with int64 microsecond time.

Polarity in memory is int8 +1/-1 (signed arithmetic on it is natural); the take file
stores it as uint8 1/0, the DSEC convention, so existing loaders read it unchanged.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rigd.core.errors import EventDataError

_EVENT_DTYPES = {"x": np.uint16, "y": np.uint16, "p": np.int8, "t": np.int64}
_TRIGGER_DTYPES = {"t": np.int64, "p": np.uint8, "channel": np.uint8}


def _check_columns(obj: Any, dtypes: dict[str, Any], kind: str) -> None:
    n = None
    for name, dt in dtypes.items():
        arr = getattr(obj, name)
        if not isinstance(arr, np.ndarray) or arr.ndim != 1:
            raise EventDataError(f"{kind}.{name} must be a 1-D numpy array")
        if arr.dtype != dt:
            raise EventDataError(f"{kind}.{name} has dtype {arr.dtype}, expected {np.dtype(dt)}")
        if n is None:
            n = arr.shape[0]
        elif arr.shape[0] != n:
            raise EventDataError(f"{kind}.{name} has {arr.shape[0]} entries, expected {n}")


@dataclass(frozen=True, slots=True)
class EventArray:
    """Change-detection events of one sensor, in one clock (device or rig)."""

    x: NDArray[np.uint16]
    y: NDArray[np.uint16]
    p: NDArray[np.int8]
    t: NDArray[np.int64]

    def __post_init__(self) -> None:
        _check_columns(self, _EVENT_DTYPES, "EventArray")

    @classmethod
    def empty(cls) -> EventArray:
        return cls(
            np.empty(0, np.uint16), np.empty(0, np.uint16), np.empty(0, np.int8), np.empty(0, np.int64)
        )

    @classmethod
    def from_arrays(cls, x: Any, y: Any, p: Any, t: Any) -> EventArray:
        """Cast from any integer arrays, checking ranges instead of wrapping silently.

        Polarity may be given as 0/1 or -1/+1; 0 means OFF.
        """
        x64, y64, p64 = (np.asarray(a, dtype=np.int64) for a in (x, y, p))
        t_arr = np.asarray(t)
        if t_arr.dtype.kind == "f":
            raise EventDataError("event time must be integer microseconds, got floating point")
        t64 = t_arr.astype(np.int64, copy=False)
        for name, arr in (("x", x64), ("y", y64)):
            if arr.size and (arr.min() < 0 or arr.max() > np.iinfo(np.uint16).max):
                raise EventDataError(f"event {name} out of uint16 range")
        if p64.size and not np.isin(p64, (-1, 0, 1)).all():
            raise EventDataError("event polarity must be in {-1, 0, 1}")
        pol = np.where(p64 > 0, 1, -1).astype(np.int8)
        return cls(x64.astype(np.uint16), y64.astype(np.uint16), pol, t64)

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def __getitem__(self, key: slice | NDArray[Any]) -> EventArray:
        return EventArray(self.x[key], self.y[key], self.p[key], self.t[key])

    @property
    def nbytes(self) -> int:
        return int(self.x.nbytes + self.y.nbytes + self.p.nbytes + self.t.nbytes)

    def is_time_sorted(self) -> bool:
        return bool(self.t.size < 2 or (np.diff(self.t) >= 0).all())

    def with_time(self, t: NDArray[np.int64]) -> EventArray:
        return EventArray(self.x, self.y, self.p, t)

    @staticmethod
    def concatenate(parts: Sequence[EventArray]) -> EventArray:
        if not parts:
            return EventArray.empty()
        return EventArray(
            np.concatenate([e.x for e in parts]),
            np.concatenate([e.y for e in parts]),
            np.concatenate([e.p for e in parts]),
            np.concatenate([e.t for e in parts]),
        )


@dataclass(frozen=True, slots=True)
class TriggerEvents:
    """External-trigger edges latched by an event sensor: p is 1 rising, 0 falling."""

    t: NDArray[np.int64]
    p: NDArray[np.uint8]
    channel: NDArray[np.uint8]

    def __post_init__(self) -> None:
        _check_columns(self, _TRIGGER_DTYPES, "TriggerEvents")

    @classmethod
    def empty(cls) -> TriggerEvents:
        return cls(np.empty(0, np.int64), np.empty(0, np.uint8), np.empty(0, np.uint8))

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def __getitem__(self, key: slice | NDArray[Any]) -> TriggerEvents:
        return TriggerEvents(self.t[key], self.p[key], self.channel[key])

    def rising(self, channel: int | None = None) -> TriggerEvents:
        mask = self.p == 1
        if channel is not None:
            mask &= self.channel == channel
        return self[mask]

    @staticmethod
    def concatenate(parts: Sequence[TriggerEvents]) -> TriggerEvents:
        if not parts:
            return TriggerEvents.empty()
        return TriggerEvents(
            np.concatenate([e.t for e in parts]),
            np.concatenate([e.p for e in parts]),
            np.concatenate([e.channel for e in parts]),
        )


@dataclass(frozen=True, slots=True)
class EvtChunk:
    """The wire bytes an event packet was decoded from, so a take can store them as sent.

    `data` holds whole words of the `fmt` stream; decoding them with a decoder whose state is
    `state` (the format's decoder state array just before the first byte, nothing held back)
    gives exactly the packet's events and trigger edges. `stream` names the byte stream (a new
    one after a reconnect), `offset` is where `data` starts in it: two chunks follow each other
    without a gap when the second starts where the first ends in the same stream.
    `shift_us`: what the capture path added to the packet's times (a restarted clock re-tied);
    the decoded times plus it are the packet's. `geometry`: (width, height) of the decoder that
    made the packet's events, which emits none outside it (it skips and counts such words), so a
    take of that geometry need not check them again.
    """

    fmt: str
    data: bytes
    state: NDArray[np.int64]
    stream: int
    offset: int
    shift_us: int = 0
    geometry: tuple[int, int] | None = None

    @property
    def end(self) -> int:
        return self.offset + len(self.data)

    def continues(self, prev: EvtChunk | None) -> bool:
        """Whether this chunk starts where `prev` ended, in the same stream."""
        return prev is not None and prev.stream == self.stream and prev.end == self.offset


@dataclass(frozen=True, slots=True)
class EventSpan:
    """How many events a packet holds and the times of its first and last one (-1 when none):
    what a capture that stores the words as sent needs of them."""

    n: int
    t_first: int
    t_last: int

    @classmethod
    def of(cls, events: EventArray) -> EventSpan:
        if not len(events):
            return cls(0, -1, -1)
        return cls(len(events), int(events.t[0]), int(events.t[-1]))

    def shifted(self, us: int) -> EventSpan:
        return self if not self.n else EventSpan(self.n, self.t_first + us, self.t_last + us)


#: Decodes a chunk's words on their own (its state, geometry and shift): `rigd.evt.decode_chunk`.
ChunkDecoder = Callable[[EvtChunk], EventArray]


class EventPacket:
    """Events and trigger edges read in one call, both in the sensor's clock; `raw`: the
    bytes they were decoded from, for sensors that send an EVT stream (None otherwise).

    A sensor that only scanned its words (`EventPacket.scanned`) gives their `span` and no
    events: the capture path needs only the span, and stores the words. `events` decodes them
    then, once, on the thread that asks (a live view, a columns take, a test)."""

    __slots__ = ("_decode", "_events", "host_time_ns", "raw", "span", "triggers")

    def __init__(
        self, events: EventArray, triggers: TriggerEvents, host_time_ns: int, raw: EvtChunk | None = None
    ) -> None:
        self._events: EventArray | None = events
        self._decode: ChunkDecoder | None = None
        self.triggers = triggers
        self.host_time_ns = host_time_ns
        self.raw = raw
        self.span = EventSpan.of(events)

    @classmethod
    def scanned(
        cls, span: EventSpan, triggers: TriggerEvents, host_time_ns: int, raw: EvtChunk, decode: ChunkDecoder
    ) -> EventPacket:
        """A packet whose words were scanned, not decoded: `decode(raw)` gives its events."""
        packet = cls.__new__(cls)
        packet._events = None
        packet._decode = decode
        packet.triggers = triggers
        packet.host_time_ns = host_time_ns
        packet.raw = raw
        packet.span = span
        return packet

    @property
    def n_events(self) -> int:
        return self.span.n

    @property
    def from_scan(self) -> bool:
        """Whether the sensor only scanned the words (the events are decoded when asked for)."""
        return self._decode is not None

    @property
    def decoded(self) -> bool:
        """Whether the events are at hand (not still to be decoded from the words)."""
        return self._events is not None

    @property
    def events(self) -> EventArray:
        if self._events is None:
            decode, raw = self._scan()
            events = decode(raw)
            if EventSpan.of(events) != self.span:
                raise EventDataError(
                    f"packet of {self.span.n} scanned events ({self.span.t_first}..{self.span.t_last} us) "
                    f"decodes to {len(events)} ({EventSpan.of(events)}): scan and decoder disagree"
                )
            self._events = events
        return self._events

    def with_shift(self, us: int, raw: EvtChunk | None) -> EventPacket:
        """The packet with `us` added to its times (`raw`: its words, with the shift noted)."""
        triggers = TriggerEvents(self.triggers.t + us, self.triggers.p, self.triggers.channel)
        if self._events is None:
            decode, _ = self._scan()
            if raw is None:
                raise EventDataError("a scanned packet's shift needs its words")
            return EventPacket.scanned(self.span.shifted(us), triggers, self.host_time_ns, raw, decode)
        return EventPacket(self._events.with_time(self._events.t + us), triggers, self.host_time_ns, raw)

    def with_triggers(self, triggers: TriggerEvents) -> EventPacket:
        """The same events and words with other trigger edges (a window gate's)."""
        if self._events is None:
            decode, raw = self._scan()
            return EventPacket.scanned(self.span, triggers, self.host_time_ns, raw, decode)
        return EventPacket(self._events, triggers, self.host_time_ns, self.raw)

    def _scan(self) -> tuple[ChunkDecoder, EvtChunk]:
        """The decoder and words of a packet made by `scanned` (both there by construction)."""
        if self._decode is None or self.raw is None:
            raise EventDataError("not a scanned packet")
        return self._decode, self.raw

    def __repr__(self) -> str:
        words = "" if self.raw is None else f", {len(self.raw.data)} B of words"
        state = "decoded" if self.decoded else "scanned"
        edges = f"{len(self.triggers)} trigger edge(s)"
        return f"EventPacket({self.span}, {edges}, host {self.host_time_ns} ns, {state}{words})"
