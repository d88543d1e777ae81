"""The EVT 3.0 scan counts exactly what the decoder decodes, and hands it what it cannot."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.testing.evt_streams import (
    DIRTY,
    SETTINGS,
    assert_same,
    encoder_stream,
    mutated,
    needs_data,
    real_body,
)
from rigd.core.errors import EventDataError
from rigd.core.events import EventArray, EventPacket, EventSpan, EvtChunk, TriggerEvents
from rigd.evt import Scanned, StreamDecoder, decode_chunk
from rigd.evt.raw import decode_bytes


def _both(data: bytes, sizes: list[int], w: int = 1280, h: int = 720) -> list[tuple[Scanned, EvtChunk]]:
    """Scan `data` in pieces of `sizes` (cycled) beside a decoder fed the same pieces; every piece's
    span, edges, chunk, decoder state and skip counts are the same. Returns the scans."""
    scan = StreamDecoder("evt3", width=w, height=h)
    dec = StreamDecoder("evt3", width=w, height=h)
    out = []
    pos = i = 0
    while pos < len(data):
        piece = data[pos : pos + sizes[i % len(sizes)]]
        pos += len(piece)
        i += 1
        scanned, chunk = scan.scan_chunk(piece)
        decoded, chunk2 = dec.feed_chunk(piece)
        assert scanned.span == EventSpan.of(decoded.events)
        assert_same(scanned.triggers, decoded.triggers)
        if scanned.events is not None:
            assert_same(scanned.events, decoded.events)
        assert chunk.data == chunk2.data
        assert chunk.offset == chunk2.offset
        np.testing.assert_array_equal(chunk.state, chunk2.state)
        np.testing.assert_array_equal(scan.state_copy(), dec.state_copy())
        assert scan.stats == dec.stats
        assert scan.bytes_consumed == dec.bytes_consumed
        out.append((scanned, chunk))
    return out


@needs_data
@pytest.mark.parametrize("step", [997, 56_000, 300_000])
def test_real_recording_scans_as_it_decodes(step: int) -> None:
    body = real_body("evt3_gen41_sample.raw")
    scans = _both(body, [step])
    assert sum(s.span.n for s, _ in scans) == len(decode_bytes(body, "evt3").events)
    if step >= 56_000:
        # a valid stream is scanned, not decoded (all but the piece before the first TIME_HIGH
        # and the one where the recording's time jumps back)
        scanned = [s for s, _ in scans if s.events is None]
        assert len(scanned) >= len(scans) - 2


@SETTINGS
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(0, 600),
    n_trig=st.integers(0, 100),
    loops=st.integers(0, 3),
    sizes=st.lists(st.integers(1, 400), min_size=1, max_size=5),
)
def test_encoder_streams_scan_as_they_decode(
    seed: int, n: int, n_trig: int, loops: int, sizes: list[int]
) -> None:
    """Vectors near the right edge, roll-overs, more trigger edges than one scan keeps."""
    _both(encoder_stream(np.random.default_rng(seed), n, n_trig, loops, 2), sizes)


@pytest.mark.slow
@SETTINGS
@given(**DIRTY)
def test_broken_words_go_to_the_decoder(
    seed: int, n_mut: int, cut: bool, geometry: tuple[int, int], sizes: list[int]
) -> None:
    rng = np.random.default_rng(seed)
    _both(mutated(rng, encoder_stream(rng, 400, 5, 2, 2), n_mut, cut=cut), sizes, *geometry)


def test_each_irregular_word_is_left_to_the_decoder() -> None:
    """One clean stretch, then each word the scan must not judge appended to it."""
    clean = [0x8001, 0x6010, 0x0005, 0x2007, 0x3100, 0x4FFF, 0x5003]
    for word in (
        0x2500,  # ADDR_X past the width
        0x02D0,  # ADDR_Y 720, then an event
        0x8000,  # TIME_HIGH falling a little (a jump back, or a corrupt word)
        0x8050,  # TIME_HIGH stepping further than TH_JUMP
        0x6000,  # TIME_LOW taking the time back, then an event
        0x9000,  # an unknown type
    ):
        words = [*clean, word, 0x2001, 0x3000, 0x4001]
        data = np.array(words, "<u2").tobytes()
        scan = StreamDecoder("evt3", width=1280, height=720)
        scan.feed(np.array([0x8001], "<u2").tobytes())  # a time base, so the scan may start
        scanned = scan.scan(data)
        assert scanned.events is not None, hex(word)
    ok = StreamDecoder("evt3", width=1280, height=720)
    ok.feed(np.array([0x8001], "<u2").tobytes())
    assert ok.scan(np.array(clean, "<u2").tobytes()).events is None


def test_a_scanned_packet_decodes_its_events_when_asked() -> None:
    body = np.array([0x8001, 0x6010, 0x0005, 0x2007, 0x3100, 0x4FFF, 0x6020, 0xA101], "<u2").tobytes()
    dec = StreamDecoder("evt3", width=1280, height=720)
    dec.feed(body[:2])
    scanned, chunk = dec.scan_chunk(body[2:])
    assert scanned.events is None
    assert scanned.span == EventSpan(13, 4096 + 16, 4096 + 16)
    packet = scanned.packet(123, chunk)
    assert packet.from_scan
    assert not packet.decoded
    assert packet.n_events == 13
    assert len(packet.triggers) == 1
    events = packet.events
    assert packet.decoded
    assert events.x.tolist() == [7, *range(0x100, 0x100 + 12)]
    assert (events.t == 4096 + 16).all()
    moved = EvtChunk(chunk.fmt, chunk.data, chunk.state, 1, 0, 1000, chunk.geometry)
    shifted = packet.with_shift(1000, moved)
    assert shifted.span == EventSpan(13, 5112, 5112)
    np.testing.assert_array_equal(shifted.events.t, events.t + 1000)
    assert shifted.triggers.t.tolist() == [4096 + 32 + 1000]


def test_a_scan_that_disagrees_with_the_decoder_is_an_error() -> None:
    chunk = EvtChunk("evt3", b"", np.zeros(10, np.int64), 1, 0, geometry=(1280, 720))
    packet = EventPacket.scanned(EventSpan(5, 0, 9), TriggerEvents.empty(), 0, chunk, decode_chunk)
    with pytest.raises(EventDataError, match="scan and decoder disagree"):
        _ = packet.events
    decoded = EventPacket(EventArray.empty(), TriggerEvents.empty(), 0)
    assert not decoded.from_scan
    assert decoded.decoded
