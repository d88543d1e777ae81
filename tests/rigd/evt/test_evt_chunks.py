"""EvtChunks: the bytes each feed decoded, with the decoder state before them, re-decode alone.

The take stores event sensors' words as sent and decodes any stored piece from the state kept
beside it, so per chunk (and per run of chunks joined) a fresh decoder started from the chunk's
state must give exactly what the live decoder gave: for any cut points, on the real Gen4.1
recording and on encoded streams with jumps back in time and chunks cut mid-word.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.testing.evt_streams import FORMATS, SETTINGS, assert_same, needs_data, real_body
from drivers.testing.evt_streams import joined as _joined
from rigd.core.errors import EventDataError
from rigd.core.events import EvtChunk
from rigd.evt import Decoded, StreamDecoder

_REAL = "evt3_gen41_sample.raw"


def _chunked(fmt: str, data: bytes, cuts: list[int]) -> tuple[list[tuple[Decoded, EvtChunk]], Decoded]:
    """Feed data cut at `cuts` with feed_chunk, then flush_chunk; also the one-feed decode."""
    dec = StreamDecoder(fmt)
    out = []
    bounds = [0, *sorted({min(max(c, 0), len(data)) for c in cuts}), len(data)]
    for a, b in itertools.pairwise(bounds):
        out.append(dec.feed_chunk(memoryview(data)[a:b]))
    tail, chunk = dec.flush_chunk()
    if chunk is not None:
        out.append((tail, chunk))
    whole = StreamDecoder(fmt)
    return out, Decoded.concatenate([whole.feed(data), whole.flush()])


def _redecode(chunk: EvtChunk) -> Decoded:
    dec = StreamDecoder(chunk.fmt, state=chunk.state)
    got = Decoded.concatenate([dec.feed(chunk.data), dec.flush()])
    assert not dec.pending, "a chunk holds whole words only"
    return got


def _check(fmt: str, data: bytes, cuts: list[int]) -> None:
    parts, whole = _chunked(fmt, data, cuts)
    chunks = [c for _, c in parts]
    for prev, cur in itertools.pairwise(chunks):
        assert cur.continues(prev)
    assert sum(len(c.data) for c in chunks) == len(data) - len(data) % {"evt3": 2, "evt2": 4}.get(fmt, 8)
    for decoded, chunk in parts:
        again = _redecode(chunk)
        assert_same(again.events, decoded.events)
        assert_same(again.triggers, decoded.triggers)
    joined = EvtChunk(fmt, b"".join(c.data for c in chunks), chunks[0].state, chunks[0].stream, 0)
    again = _redecode(joined)
    assert_same(again.events, whole.events)
    assert_same(again.triggers, whole.triggers)


@pytest.mark.slow
@needs_data
@SETTINGS
@given(cuts=st.lists(st.integers(0, 1 << 22), min_size=1, max_size=12))
def test_real_stream_chunks_redecode_from_their_state(cuts: list[int]) -> None:
    data = real_body(_REAL)[: 1 << 22]
    _check("evt3", data, cuts)


@SETTINGS
@given(
    fmt=st.sampled_from(FORMATS),
    seed=st.integers(0, 2**32 - 1),
    jump=st.integers(1, 45),
    cuts=st.lists(st.integers(0, 1 << 16), min_size=1, max_size=20),
)
def test_chunks_across_time_jumps_redecode_from_their_state(
    fmt: str, seed: int, jump: int, cuts: list[int]
) -> None:
    """Jumps back (held words at feed ends) and cuts mid-word (a partial word pending)."""
    _, _, data = _joined(fmt, seed, jump)
    _check(fmt, data, [c % (len(data) + 1) for c in cuts])


@pytest.mark.slow
@pytest.mark.parametrize("fmt", FORMATS)
def test_held_words_leave_the_state_at_their_start(fmt: str) -> None:
    """Cut just past a jump's TIME_HIGH: the decoder holds it back, and the next chunk, which
    begins with it, starts from the state its first word needs."""
    a, _, data = _joined(fmt, 7)
    word = {"evt3": 2, "evt2": 4, "evt21": 8, "evt21_le": 8}[fmt]
    dec = StreamDecoder(fmt)
    _, first = dec.feed_chunk(data[: len(a) + word + 1])
    assert dec.holding
    assert len(first.data) == len(a)
    _, second = dec.feed_chunk(data[len(a) + word + 1 :])
    assert second.continues(first)
    assert second.data[:word] == data[len(a) : len(a) + word]
    _check(fmt, data, [len(a) + word + 1])


def test_state_of_the_wrong_size_is_refused() -> None:
    with pytest.raises(EventDataError, match="state must be 10"):
        StreamDecoder("evt3", state=np.zeros(6, np.int64))
