"""EVT 3.0 time words: a stream tells how far it got with no event, and a reader sees it."""

from __future__ import annotations

import numpy as np

from rigd.core.events import EventArray, TriggerEvents
from rigd.evt import Evt3Encoder, StreamDecoder


def _events(t: list[int]) -> EventArray:
    n = len(t)
    return EventArray(
        np.arange(n, dtype=np.uint16), np.zeros(n, np.uint16), np.ones(n, np.int8), np.asarray(t, np.int64)
    )


def test_time_marks_move_the_decoders_time_without_events() -> None:
    enc = Evt3Encoder()
    dec = StreamDecoder("evt3", width=64, height=8)
    assert dec.time_us is None
    got = dec.feed(enc.encode(_events([10, 20, 30])))
    assert len(got.events) == 3
    assert dec.time_us == 30
    for mark in (4_095, 4_096, 9_000_123, 40_000_000):  # inside a TIME_HIGH, across, far, past a loop
        got = dec.feed(enc.mark_time(mark))
        assert len(got.events) == 0
        assert dec.time_us == mark
    # events after a mark decode at their own times
    got = dec.feed(enc.encode(_events([40_000_001, 40_000_500]), TriggerEvents.empty()))
    assert got.events.t.tolist() == [40_000_001, 40_000_500]


def test_a_mark_behind_the_stream_moves_nothing() -> None:
    enc = Evt3Encoder()
    dec = StreamDecoder("evt3", width=64, height=8)
    dec.feed(enc.encode(_events([5_000])))
    assert enc.mark_time(100) == b""
    assert dec.time_us == 5_000


def test_other_formats_do_not_say() -> None:
    assert StreamDecoder("evt2", width=64, height=8).time_us is None


def test_a_corrupt_time_high_does_not_move_the_paced_time() -> None:
    """One corrupt TIME_HIGH word in a recording: the decoder drops the word, and the time points
    a paced replay cuts the stream by agree with it (before: the word's step forward, taken as
    time, held every later byte back; its fall back read as a roll-over of the 24-bit counter)."""
    from rigd.evt.timepoints import time_points

    t = list(range(0, 60_000, 50))
    raw = bytearray(Evt3Encoder().encode(_events(t)))
    words = np.frombuffer(raw, "<u2").copy()
    highs = np.flatnonzero((words >> 12) == 0x8)
    k = int(highs[len(highs) // 2])
    th = int(words[k]) & 0xFFF
    words[k] = 0x8000 | ((th + 1800) & 0xFFF)  # a corrupt word: far ahead of its neighbours
    got = StreamDecoder("evt3", width=2048, height=8).feed(words.tobytes())
    assert got.events.t.max() == t[-1]  # the decoder dropped only the word
    _, tp, last = time_points(words, "evt3")
    assert last <= t[-1]
    assert int(tp.max()) <= t[-1]
