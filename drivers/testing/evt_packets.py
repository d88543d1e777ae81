"""Event packets as a streaming sensor delivers them: decoded from EVT words, raw chunk attached."""

from __future__ import annotations

from collections.abc import Iterator

from rigd.core.events import EventArray, EventPacket
from rigd.evt import Scanned, StreamDecoder, encode


def packets_from_bytes(
    fmt: str, data: bytes, piece: int, *, width: int = 1280, height: int = 720, scan: bool = False
) -> Iterator[EventPacket]:
    """`data` fed in pieces of `piece` bytes; a packet per feed with events or edges (the bytes
    of feeds that decoded to nothing are carried into the next packet, as the sensor does).
    `scan`: the words are scanned, not decoded, where they can be (as the capture's sensors do)."""
    dec = StreamDecoder(fmt, width=width, height=height)
    carry = None
    for pos in range(0, len(data), piece):
        got, chunk = (
            dec.scan_chunk(data[pos : pos + piece]) if scan else dec.feed_chunk(data[pos : pos + piece])
        )
        if carry is not None:
            chunk = type(chunk)(
                fmt, carry.data + chunk.data, carry.state, carry.stream, carry.offset, geometry=chunk.geometry
            )
            carry = None
        if isinstance(got, Scanned):
            if not got.empty:
                yield got.packet(pos, chunk)
            elif chunk.data:
                carry = chunk
        elif len(got.events) or len(got.triggers):
            yield EventPacket(got.events, got.triggers, pos, chunk)
        elif chunk.data:
            carry = chunk
    got, last = dec.flush_chunk()
    if last is not None and (len(got.events) or len(got.triggers)):
        yield EventPacket(got.events, got.triggers, len(data), last)


def packets_of(events: EventArray, piece: int, *, width: int, height: int) -> list[EventPacket]:
    """Events encoded as EVT 3.0 and decoded back in packets (the times they decode to are the
    events' own: the encoder is exact)."""
    return list(packets_from_bytes("evt3", encode("evt3", events), piece, width=width, height=height))
