"""A consistent jump back in stream time is a recorded discontinuity, not the loss of what follows.

Two streams joined (or a sensor re-based back): the events after the join are kept, shifted so
the new TIME_HIGH base follows the old one by one period, and the jump is recorded. A single
corrupt TIME_HIGH that falls is still skipped as before. Streams are generated per format with
the encoders; the decoder is fed in random chunks, so jumps straddle its buffer boundaries.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.file_event_sensor import FileEventSensor
from drivers.testing.evt_streams import (
    FORMATS,
    SETTINGS,
    SHIFT,
    WORD,
    FixedStream,
    assert_same,
    feed_chunks,
    needs_data,
    real_body,
)
from drivers.testing.evt_streams import joined as _joined
from drivers.testing.evt_streams import segment as _segment
from drivers.testing.evt_streams import time_highs as _time_highs
from rigd.core.errors import EventDataError
from rigd.core.events import TriggerEvents
from rigd.evt import (
    JUMP_CONFIRM,
    Decoded,
    EvtDecodeError,
    RawHeader,
    RawReader,
    StreamDecoder,
    decode_bytes,
)
from rigd.evt.jumps import MAX_KEPT_JUMPS
from rigd.products.convert import convert
from rigd.take.reader import Take


def _decode(data: bytes, fmt: str, sizes: list[int], **kw: int) -> tuple[Decoded, StreamDecoder]:
    dec = StreamDecoder(fmt, **kw)  # type: ignore[arg-type]
    return Decoded.concatenate(list(feed_chunks(dec, data, sizes))), dec


def _same(a: Decoded, b: Decoded) -> None:
    assert_same(a.events, b.events)
    assert_same(a.triggers, b.triggers)


def _shifted(d: Decoded, us: int) -> Decoded:
    tr = d.triggers
    return Decoded(d.events.with_time(d.events.t + us), TriggerEvents(tr.t + us, tr.p, tr.channel))


def _count(d: Decoded) -> int:
    return len(d.events) + len(d.triggers)


@SETTINGS
@given(
    fmt=st.sampled_from(FORMATS),
    seed=st.integers(0, 2**32 - 1),
    back=st.booleans(),
    jump=st.integers(0, 300),
    periods=st.tuples(st.integers(1, 40), st.integers(1, 40)),
    per_period=st.integers(1, 6),
    sizes=st.lists(st.integers(1, 3000), min_size=1, max_size=4),
)
def test_jump_back_is_kept_and_recorded_jump_forward_is_taken(
    fmt: str, seed: int, back: bool, jump: int, periods: tuple[int, int], per_period: int, sizes: list[int]
) -> None:
    """Two streams joined, the second starting `jump` periods (plus a fraction) before or after
    where the first ended. Back: kept when JUMP_CONFIRM TIME_HIGH values of the second stay below
    the first's last (shifted by whole periods to follow on, one jump recorded), else every event
    is kept or counted as dropped. Forward: taken as it comes (OpenEB's semantics)."""
    rng = np.random.default_rng(seed)
    s = SHIFT[fmt]
    a0 = int(rng.integers(300 << s, 600 << s))
    a = _segment(fmt, rng, a0, periods[0], per_period)
    ref_a = decode_bytes(a, fmt)
    a_th = int(_time_highs(a, fmt)[1][-1])  # the first stream's last TIME_HIGH
    a_end = max(int(x[-1]) for x in (ref_a.events.t, ref_a.triggers.t) if len(x))
    b0 = a_end + (-1 if back else 1) * ((jump << s) + int(rng.integers(0, 1 << s)))
    b = _segment(fmt, rng, max(0, b0), periods[1], per_period)
    ref_b = decode_bytes(b, fmt)
    got, dec = _decode(a + b, fmt, sizes)
    whole, whole_dec = _decode(a + b, fmt, [len(a + b)])
    _same(got, whole)  # wherever the chunks were cut
    assert dec.jumps == whole_dec.jumps
    assert dec.stats == whole_dec.stats
    assert got.events.is_time_sorted()
    assert bool(np.all(np.diff(got.triggers.t) >= 0))
    _same(Decoded(got.events[: len(ref_a.events)], got.triggers[: len(ref_a.triggers)]), ref_a)
    b_ths = np.unique(_time_highs(b, fmt)[1])
    b_th = int(b_ths[0])
    if back and b_th < a_th and np.count_nonzero(b_ths < a_th) >= JUMP_CONFIRM:
        shift = (a_th - b_th + 1) << s
        _same(got, Decoded.concatenate([ref_a, _shifted(ref_b, shift)]))
        assert dec.time_jumps == 1
        assert not any(dec.stats.values())
        (j,) = dec.jumps
        assert (j.offset, j.old_base_us, j.new_base_us, j.shift_us) == (len(a), a_th << s, b_th << s, shift)
        confirm_at = int(_time_highs(b, fmt)[0][np.flatnonzero(_time_highs(b, fmt)[1] == b_ths[1])[0]])
        assert j.held_events == len(decode_bytes(b[: confirm_at * WORD[fmt]], fmt).events)
        assert dec.jump_stats["time_jumps"] == 1
    elif not back and b_th > a_th:
        _same(got, Decoded.concatenate([ref_a, ref_b]))
        assert dec.time_jumps == 0
        assert not any(dec.stats.values())
    else:  # a jump too short to tell from a corrupt word (or none): kept or counted, as before
        assert dec.time_jumps == 0
        assert _count(got) + dec.stats["non_monotonic_time"] == _count(ref_a) + _count(ref_b)


@SETTINGS
@given(
    fmt=st.sampled_from(FORMATS),
    seed=st.integers(0, 2**32 - 1),
    where=st.floats(0.05, 0.95),
    fall=st.integers(1, 2047),
    whole_word=st.booleans(),
    sizes=st.lists(st.integers(1, 3000), min_size=1, max_size=4),
)
def test_single_corrupt_time_high_is_still_rejected(
    fmt: str, seed: int, where: float, fall: int, whole_word: bool, sizes: list[int]
) -> None:
    """One word (a TIME_HIGH, or any word when `whole_word`) replaced by a TIME_HIGH that falls:
    never taken for a jump; skipped as non_monotonic_time_high and, when it replaced a
    TIME_HIGH, every event is kept or counted as dropped."""
    rng = np.random.default_rng(seed)
    data = _segment(fmt, rng, int(rng.integers(3000 << SHIFT[fmt], 4000 << SHIFT[fmt])), 60, 3)
    ref = decode_bytes(data, fmt)
    idx, val = _time_highs(data, fmt)
    ws = WORD[fmt]
    if whole_word:
        i = int(where * (len(data) // ws))
        th = int(val[np.flatnonzero(idx < i)[-1]])
    else:
        k = max(1, int(where * len(idx)))
        i, th = int(idx[k]), int(val[k - 1])
    v = th - min(fall, th)
    word = (8 << 12 | v) if fmt == "evt3" else (8 << 28 | v)
    buf = bytearray(data)
    off = i * ws + (4 if fmt == "evt21_le" else 0)
    hs = 2 if fmt == "evt3" else 4
    buf[off : off + hs] = word.to_bytes(hs, "little")
    if fmt.startswith("evt21"):  # a TIME_HIGH's mask half is 0
        moff = i * ws + (0 if fmt == "evt21_le" else 4)
        buf[moff : moff + 4] = bytes(4)
    got, dec = _decode(bytes(buf), fmt, sizes)
    assert dec.time_jumps == 0
    assert not dec.jumps
    assert dec.stats["non_monotonic_time_high"] == (1 if v < th else 0)
    assert got.events.is_time_sorted()
    if not whole_word:
        assert _count(got) + dec.stats["non_monotonic_time"] == _count(ref)
    if v < th:
        with pytest.raises(EvtDecodeError, match="non_monotonic_time_high") as exc:
            decode_bytes(bytes(buf), fmt, strict=True)
        assert exc.value.offset == i * ws


@pytest.mark.parametrize("fmt", FORMATS)
def test_jump_straddling_every_cut_near_it(fmt: str) -> None:
    """Chunks cut at every byte around the jump and through its confirming words, one byte at a
    time too: the same events, stats and record as one feed; the words are held meanwhile."""
    a, _, data = _joined(fmt, 1)
    whole, whole_dec = _decode(data, fmt, [len(data)])
    assert whole_dec.time_jumps == 1
    ws = WORD[fmt]
    for cut in range(len(a) - 3 * ws, len(a) + 40 * ws, 1 if ws == 2 else 3):
        for sizes in ([cut, 1 << 20], [cut, 1, 2, 3, 5, 7, 11, 1 << 20]):
            got, dec = _decode(data, fmt, sizes)
            _same(got, whole)
            assert dec.jumps == whole_dec.jumps
            assert dec.stats == whole_dec.stats
    dec = StreamDecoder(fmt)
    dec.feed(data[: len(a) + ws])
    assert dec.holding
    assert dec.time_jumps == 0
    dec.feed(data[len(a) + ws :])
    assert not dec.holding
    assert dec.time_jumps == 1


@pytest.mark.parametrize("fmt", FORMATS)
def test_jump_confirm_setting(fmt: str) -> None:
    """A jump whose second stream has exactly two TIME_HIGH values below the old one: accepted
    with the default (2), rejected with 3 (its events kept or counted as dropped, as before);
    fewer than 2 would take a corrupt word for a jump and is refused."""
    s = SHIFT[fmt]
    rng = np.random.default_rng(3)
    a = _segment(fmt, rng, 1000 << s, 20, 4)
    a_th = int(_time_highs(a, fmt)[1][-1])
    b = _segment(fmt, rng, (a_th - 2) << s, 20, 4)
    assert np.count_nonzero(np.unique(_time_highs(b, fmt)[1]) < a_th) == 2
    total = _count(decode_bytes(a, fmt)) + _count(decode_bytes(b, fmt))
    got, dec = _decode(a + b, fmt, [777])
    assert dec.time_jumps == 1
    assert _count(got) == total
    got, dec = _decode(a + b, fmt, [777], jump_confirm=3)
    assert dec.time_jumps == 0
    assert dec.stats["non_monotonic_time_high"] >= 1
    assert _count(got) + dec.stats["non_monotonic_time"] == total
    with pytest.raises(EventDataError, match=r"jump_confirm 1 outside 2\.\.64"):
        StreamDecoder(fmt, jump_confirm=1)


@pytest.mark.parametrize("fmt", FORMATS)
def test_strict_mode_accepts_a_confirmed_jump(fmt: str) -> None:
    _, _, data = _joined(fmt, 4)
    assert _count(decode_bytes(data, fmt, strict=True)) == _count(decode_bytes(data, fmt))


@pytest.mark.parametrize("fmt", ["evt3", "evt2"])
def test_many_jumps_are_all_kept_and_counted(fmt: str) -> None:
    """One stream tiled 20 times: 19 jumps (more than one kernel call records), all kept; the
    first MAX_KEPT_JUMPS in full, each later one shifted by one more span."""
    rng = np.random.default_rng(5)
    one = _segment(fmt, rng, 1000 << SHIFT[fmt], 8, 3)
    ref = decode_bytes(one, fmt)
    got, dec = _decode(one * 20, fmt, [len(one) * 20])
    assert _count(got) == 20 * _count(ref)
    assert not any(dec.stats.values())
    assert dec.time_jumps == 19
    assert len(dec.jumps) == MAX_KEPT_JUMPS
    step = dec.jumps[0].shift_us
    assert [j.shift_us for j in dec.jumps] == [step * (k + 1) for k in range(MAX_KEPT_JUMPS)]
    assert [j.offset for j in dec.jumps] == [len(one) * (k + 1) for k in range(MAX_KEPT_JUMPS)]
    last = Decoded(got.events[-len(ref.events) :], got.triggers[-len(ref.triggers) :])
    _same(last, _shifted(ref, 19 * step))


# ------------------------------------------------------------------ real recordings


@needs_data
@pytest.mark.parametrize(
    ("name", "fmt"), [("evt3_gen41_sample.raw", "evt3"), ("evt2_gen3_sample.raw", "evt2")]
)
def test_real_recording_tiled(name: str, fmt: str) -> None:
    """The real bytes joined to themselves (before: 309,077 of 439,192 Gen4.1 events kept): every
    copy's events kept, each shifted to follow the one before, one jump per join."""
    w, h = (1280, 720) if fmt == "evt3" else (640, 480)
    body = real_body(name)
    ref = decode_bytes(body, fmt, width=w, height=h)
    for k in (2, 3):
        got, dec = _decode(body * k, fmt, [1 << 20], width=w, height=h)
        assert _count(got) == k * _count(ref)
        assert not any(dec.stats.values())
        assert dec.time_jumps == k - 1
        assert [j.offset for j in dec.jumps] == [len(body) * i for i in range(1, k)]
        n = len(ref.events)
        for i in range(k):
            shift = dec.jumps[i - 1].shift_us if i else 0
            assert_same(got.events[i * n : (i + 1) * n], ref.events.with_time(ref.events.t + shift))
        assert got.events.is_time_sorted()


@needs_data
def test_convert_and_file_replay_of_a_joined_recording(tmp_path: Path) -> None:
    """`rigd convert` writes every event of a joined recording and names the jump in the take's
    warnings; a file:// replay reports it in its counters."""
    body = real_body("evt3_gen41_sample.raw")
    src = tmp_path / "joined.raw"
    src.write_bytes(RawHeader(fmt="evt3", width=1280, height=720).to_bytes() + body * 2)
    ref = decode_bytes(body, "evt3")
    assert convert(src, tmp_path / "t.h5") == 2 * len(ref.events)
    with Take(tmp_path / "t.h5") as take:
        report = take.sync_report
        assert take.sensor("ev0").count == 2 * len(ref.events)
    assert report is not None
    assert not report.losses
    hdr = len(RawHeader(fmt="evt3", width=1280, height=720).to_bytes())
    assert any(f"jumped back at byte offset {hdr + len(body)}" in line for line in report.warnings)
    sensor = FileEventSensor(src, chunk_bytes=65536)
    sensor.start()
    n = 0
    while (p := sensor.read_events(0.0)) is not None:
        n += len(p.events)
    extra = sensor.stats().extra
    sensor.close()
    assert n == 2 * len(ref.events)
    assert extra["decoder_time_jumps"] == 1
    assert extra["decoder_time_jump_first_offset"] == hdr + len(body)


@needs_data
def test_reader_yields_what_is_decided_at_the_end(tmp_path: Path) -> None:
    """A jump in the last words of a file is decided when the file ends (RawReader's last chunk)."""
    body = real_body("evt3_gen41_sample.raw")
    src = tmp_path / "j.raw"
    src.write_bytes(RawHeader(fmt="evt3", width=1280, height=720).to_bytes() + body + body[:40])
    whole = decode_bytes(body + body[:40], "evt3")
    parts = list(RawReader(src, chunk_bytes=4096))
    assert sum(len(p.events) for p in parts) == len(whole.events)


# ------------------------------------------------------------------ live stream


def _live(data: bytes, fmt: str) -> tuple[Decoded, dict[str, int]]:
    """Read a live sensor to its end, stop it and read what the stop releases."""
    sensor = FixedStream(data, 333, fmt)
    sensor.start()
    packets = sensor.read_all()
    sensor.stop()
    packets += sensor.read_all()
    extra = sensor.stats().extra
    sensor.close()
    return Decoded.concatenate([Decoded(p.events, p.triggers) for p in packets]), extra


@pytest.mark.parametrize("fmt", ["evt3", "evt2"])
def test_live_stream_keeps_a_jump_and_counts_it(fmt: str) -> None:
    """The capture path: every event kept, the jump in the device counters (decoder_time_*)."""
    a, b, data = _joined(fmt, 6)
    got, extra = _live(data, fmt)
    assert _count(got) == _count(decode_bytes(a, fmt)) + _count(decode_bytes(b, fmt))
    assert got.events.is_time_sorted()
    assert extra["decoder_time_jumps"] == 1
    assert extra["decoder_time_jump_first_offset"] == len(a)
    assert extra["decoder_time_jump_first_shift_us"] > 0


@pytest.mark.parametrize("fmt", ["evt3", "evt2"])
def test_live_stream_that_stops_while_a_jump_is_unconfirmed(fmt: str) -> None:
    """The stream ends one TIME_HIGH value after a fall: held until the sensor stops, then
    decided as a corrupt word; what it held is delivered or counted as dropped."""
    a, b, _ = _joined(fmt, 7)
    idx, val = _time_highs(b, fmt)
    cut = int(idx[np.flatnonzero(val > val[0])[0]]) * WORD[fmt]  # before b's second TIME_HIGH value
    got, extra = _live(a + b[:cut], fmt)
    total = _count(decode_bytes(a, fmt)) + _count(decode_bytes(b[:cut], fmt))
    assert "decoder_time_jumps" not in extra
    assert extra["decoder_skipped_non_monotonic_time_high"] >= 1
    assert _count(got) + extra["decoder_skipped_non_monotonic_time"] == total
