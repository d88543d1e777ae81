"""A corrupt word costs the events it corrupts, not the recording: output time never runs back.

Each case corrupts one word (or truncates) a clean stream and checks, against the clean decode:
the events before the corruption are kept exactly, the events after the time base is
re-established (the next TIME_HIGH, then the next row address) are kept exactly, the output is
time-sorted, dropped events are counted as non_monotonic_time with the byte offset of the first,
and strict mode raises at the first violation.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from drivers.testing.evt_streams import DATA, FixedStream, assert_same, feed_chunks, real_body
from rigd.core.events import EventArray, TriggerEvents
from rigd.evt import (
    EvtDecodeError,
    StreamDecoder,
    decode_bytes,
    encode,
    read_dat,
    write_dat,
)

WORD = {"evt3": 2, "evt2": 4, "evt21": 8, "evt21_le": 8}


def _synthetic(fmt: str, seed: int = 5) -> bytes:
    """Dense time-sorted events (several per TIME_LOW, same-row runs) and a few trigger edges."""
    rng = np.random.default_rng(seed)
    n = 6000
    t = np.sort(rng.integers(0, 1 << 21, n))
    t = np.where(rng.random(n) < 0.4, np.r_[t[:1], t[:-1]], t)
    t = np.maximum.accumulate(t)
    ev = EventArray.from_arrays(rng.integers(0, 1280, n), rng.integers(0, 720, n), rng.integers(0, 2, n), t)
    tt = np.sort(rng.integers(0, 1 << 21, 12)).astype(np.int64)
    tr = TriggerEvents(tt, rng.integers(0, 2, 12).astype(np.uint8), rng.integers(0, 8, 12).astype(np.uint8))
    return encode(fmt, ev, tr)


def _streams() -> list[tuple[str, str, bytes]]:
    out = [(f"synthetic-{f}", f, _synthetic(f)) for f in WORD]
    if DATA.is_dir():
        out += [
            ("gen41", "evt3", real_body("evt3_gen41_sample.raw")),
            ("gen3", "evt2", real_body("evt2_gen3_sample.raw")),
        ]
    return out


STREAMS = _streams()


def _types(data: bytes, fmt: str) -> np.ndarray:
    """Each whole word's type nibble."""
    if fmt == "evt3":
        return np.frombuffer(data, "<u2", len(data) // 2) >> 12
    u32 = np.frombuffer(data, "<u4", len(data) // 4)
    if fmt == "evt2":
        return u32 >> 28
    return u32[0::2] >> 28 if fmt == "evt21" else u32[1::2] >> 28


def _set_word(data: bytes, fmt: str, i: int, fn: Callable[[int], int]) -> bytes:
    """data with word i's type/time half replaced by fn(half)."""
    buf = bytearray(data)
    ws = WORD[fmt]
    half_off = i * ws + (4 if fmt == "evt21_le" else 0)
    hs = 2 if fmt == "evt3" else 4
    old = int.from_bytes(buf[half_off : half_off + hs], "little")
    buf[half_off : half_off + hs] = (fn(old) & ((1 << (8 * hs)) - 1)).to_bytes(hs, "little")
    return bytes(buf)


def _half(data: bytes, fmt: str, i: int) -> int:
    """Word i's type/time half."""
    hs = 2 if fmt == "evt3" else 4
    off = i * WORD[fmt] + (4 if fmt == "evt21_le" else 0)
    return int.from_bytes(data[off : off + hs], "little")


def _count(data: bytes, fmt: str, w: int, h: int) -> int:
    return len(decode_bytes(data, fmt, width=w, height=h).events)


def _geometry(name: str) -> tuple[int, int]:
    return (640, 480) if name == "gen3" else (1280, 720)


def _decode(
    data: bytes, fmt: str, w: int, h: int, chunk: int = 4093
) -> tuple[EventArray, TriggerEvents, StreamDecoder]:
    dec = StreamDecoder(fmt, width=w, height=h)
    parts = list(feed_chunks(dec, data, [chunk]))
    return (
        EventArray.concatenate([p.events for p in parts]),
        TriggerEvents.concatenate([p.triggers for p in parts]),
        dec,
    )


def _check(
    clean: bytes, bad: bytes, fmt: str, i: int, w: int, h: int, *, same_count: bool = False, chunk: int = 4093
) -> StreamDecoder:
    """The corrupted stream (word i changed) against the clean one; returns the decoder."""
    ws = WORD[fmt]
    ref = decode_bytes(clean, fmt, width=w, height=h)
    ev, tr, dec = _decode(bad, fmt, w, h, chunk)
    assert (np.diff(ev.t) >= 0).all()
    assert (np.diff(tr.t) >= 0).all()
    before = _count(clean[: i * ws], fmt, w, h)
    assert_same(ev[:before], ref.events[:before])
    # the time base is re-established at the next TIME_HIGH; EVT3 also needs the next row address
    types = _types(clean, fmt)
    th = np.flatnonzero(types[i + 1 :] == 8)
    if th.size:
        anchor = i + 1 + int(th[0])
        if fmt == "evt3":
            later = np.flatnonzero(types[anchor:] == 0)
            anchor = anchor + int(later[0]) if later.size else len(types)
        after = len(ref.events) - _count(clean[: anchor * ws], fmt, w, h)
        assert after <= len(ev) - before
        if after:
            assert_same(ev[len(ev) - after :], ref.events[len(ref.events) - after :])
    dropped = dec.stats["non_monotonic_time"]
    if same_count:  # only times were corrupted: every event is kept or counted
        assert len(ev) + dropped == len(ref.events)
    if dropped:
        assert dec.skipped_offsets
        assert dec.skipped_offsets[0] >= i * ws
    return dec


def _pick(types: np.ndarray, want: int, rng: np.random.Generator, k: int) -> list[int]:
    """k word indices of type `want` from the middle half of the stream."""
    idx = np.flatnonzero(types == want)
    idx = idx[(idx > len(types) // 4) & (idx < 3 * len(types) // 4)]
    return sorted(rng.choice(idx, min(k, idx.size), replace=False).tolist())


@pytest.mark.slow
@pytest.mark.parametrize(("name", "fmt", "data"), STREAMS, ids=[s[0] for s in STREAMS])
def test_zeroed_time_low(name: str, fmt: str, data: bytes) -> None:
    """EVT3: TIME_LOW's value zeroed (its events fall back in time) and the whole word zeroed (an
    ADDR_Y 0 instead); EVT 2.x: an event's 6-bit ts zeroed."""
    w, h = _geometry(name)
    rng = np.random.default_rng(1)
    types = _types(data, fmt)
    total = 0
    if fmt == "evt3":
        for i in _pick(types, 6, rng, 12):
            dec = _check(data, _set_word(data, fmt, i, lambda v: 0x6000), fmt, i, w, h, same_count=True)
            total += dec.stats["non_monotonic_time"]
            _check(data, _set_word(data, fmt, i, lambda v: 0), fmt, i, w, h, same_count=True)
    else:
        for i in _pick(types, 1, rng, 12) + _pick(types, 0, rng, 12):
            dec = _check(
                data, _set_word(data, fmt, i, lambda v: v & ~(0x3F << 22)), fmt, i, w, h, same_count=True
            )
            total += dec.stats["non_monotonic_time"]
    assert total > 0  # some of these corruptions did take time back


@pytest.mark.slow
@pytest.mark.parametrize(("name", "fmt", "data"), STREAMS, ids=[s[0] for s in STREAMS])
def test_corrupt_time_high(name: str, fmt: str, data: bytes) -> None:
    """A TIME_HIGH that falls a little (skipped), and one zeroed whole (EVT3: an ADDR_Y 0; EVT2:
    an event at 0,0 with ts 0)."""
    w, h = _geometry(name)
    rng = np.random.default_rng(2)
    types = _types(data, fmt)
    mask = 0xFFF if fmt == "evt3" else 0xFFFFFFF
    picked = _pick(types, 8, rng, 8)
    for i in picked:
        prev = i - 1 - int(np.flatnonzero(types[:i][::-1] == 8)[0])  # the TIME_HIGH before
        below = max(0, (_half(data, fmt, prev) & mask) - 1)  # a small fall from it: skipped
        dec = _check(
            data, _set_word(data, fmt, i, lambda v, b=below: (v & ~mask) | b), fmt, i, w, h, same_count=True
        )
        assert dec.stats["non_monotonic_time_high"] == 1
        _check(data, _set_word(data, fmt, i, lambda v: 0), fmt, i, w, h)


@pytest.mark.slow
@pytest.mark.parametrize(("name", "fmt", "data"), STREAMS, ids=[s[0] for s in STREAMS])
def test_time_high_jump_is_refuted_by_the_next_one(name: str, fmt: str, data: bytes) -> None:
    """A TIME_HIGH zeroed (on the Gen4.1 file, above 2048: read alone, a roll-over) or set to a
    random value (a jump): the next TIME_HIGH continues the old base, so the word is skipped as
    time_high_jump / non_monotonic_time_high and only one TIME_HIGH period's events are lost.
    The check looks ahead within the bytes of one feed (a 1 MiB chunk for files)."""
    w, h = _geometry(name)
    rng = np.random.default_rng(13)
    bits = 12 if fmt == "evt3" else 28
    jumps = 0
    for i in _pick(_types(data, fmt), 8, rng, 10):
        for val in (0, int(rng.integers(0, 1 << bits))):
            bad = _set_word(data, fmt, i, lambda v, x=val: (8 << bits) | x)
            jumps += _check(data, bad, fmt, i, w, h, chunk=len(data)).stats["time_high_jump"]
    assert jumps > 0


@pytest.mark.slow
@pytest.mark.parametrize(("name", "fmt", "data"), STREAMS, ids=[s[0] for s in STREAMS])
def test_random_words_and_flipped_bits(name: str, fmt: str, data: bytes) -> None:
    """A random word (any type but TIME_HIGH, whose random values OpenEB reads as a roll-over or
    a jump) anywhere, and one flipped bit in an event or vector word."""
    w, h = _geometry(name)
    rng = np.random.default_rng(3)
    types = _types(data, fmt)
    n = len(types)
    for i in sorted(rng.integers(n // 4, 3 * n // 4, 15).tolist()):
        typ = int(rng.choice([t for t in range(16) if t != 8]))
        shift = 12 if fmt == "evt3" else 28
        val = (typ << shift) | int(rng.integers(0, 1 << shift))
        _check(data, _set_word(data, fmt, i, lambda v, val=val: val), fmt, i, w, h)
    vec = (4, 5, 2) if fmt == "evt3" else (0, 1)
    for i in _pick(np.where(np.isin(types, vec), 99, types), 99, rng, 15):
        bit = int(rng.integers(0, 12 if fmt == "evt3" else 28))
        _check(data, _set_word(data, fmt, i, lambda v, bit=bit: v ^ (1 << bit)), fmt, i, w, h)


@pytest.mark.slow
@pytest.mark.parametrize(("name", "fmt", "data"), STREAMS, ids=[s[0] for s in STREAMS])
def test_truncation_at_many_offsets(name: str, fmt: str, data: bytes) -> None:
    w, h = _geometry(name)
    ref = decode_bytes(data, fmt, width=w, height=h)
    rng = np.random.default_rng(4)
    ws = WORD[fmt]
    cuts = sorted({*rng.integers(0, len(data), 40).tolist(), 0, 1, len(data) - 1, len(data) - ws + 1})
    for cut in cuts:
        ev, _, dec = _decode(data[:cut], fmt, w, h)
        assert_same(ev, ref.events[: len(ev)])
        assert dec.stats["truncated"] == (1 if cut % ws else 0)
        assert not dec.stats["non_monotonic_time"]
        if cut % ws:
            assert dec.skipped_offsets[-1] == cut - cut % ws
            with pytest.raises(EvtDecodeError, match="truncated") as exc:
                decode_bytes(data[:cut], fmt, width=w, height=h, strict=True)
            assert exc.value.offset == cut - cut % ws


@pytest.mark.parametrize("fmt", list(WORD))
def test_strict_raises_at_the_first_backwards_event(fmt: str) -> None:
    data = _synthetic(fmt)
    types = _types(data, fmt)
    want, fn = (6, lambda v: 0x6000) if fmt == "evt3" else (1, lambda v: v & ~(0x3F << 22))
    for i in _pick(types, want, np.random.default_rng(6), 20):
        bad = _set_word(data, fmt, i, fn)
        dec = StreamDecoder(fmt)
        dec.feed(bad)
        if dec.stats["non_monotonic_time"]:
            with pytest.raises(EvtDecodeError, match="non_monotonic_time at byte offset") as exc:
                decode_bytes(bad, fmt, strict=True)
            assert exc.value.offset == dec.skipped_offsets[0]
            assert exc.value.kind == "non_monotonic_time"
            return
    pytest.fail("no corruption took time back")


def test_skipped_offsets_are_kept_across_chunks_and_capped() -> None:
    data = _synthetic("evt3")
    types = _types(data, "evt3")
    bad = data
    picked = _pick(types, 6, np.random.default_rng(7), 40)
    for i in picked:
        bad = _set_word(bad, "evt3", i, lambda v: 0x6000)
    whole = StreamDecoder("evt3")
    whole.feed(bad)
    chunked = StreamDecoder("evt3")
    list(feed_chunks(chunked, bad, [7, 1000, 3]))
    assert chunked.skipped_offsets == whole.skipped_offsets
    assert 0 < len(whole.skipped_offsets) <= 8
    assert all(o in {2 * i for i in picked} or o > 2 * picked[0] for o in whole.skipped_offsets)
    assert chunked.stats == whole.stats


# ------------------------------------------------------------------ DAT


def _dat(tmp_path: Path) -> tuple[Path, EventArray, int]:
    rng = np.random.default_rng(8)
    n = 3000
    ev = EventArray.from_arrays(
        rng.integers(0, 640, n),
        rng.integers(0, 480, n),
        rng.integers(0, 2, n),
        np.sort(rng.integers(1000, 10**7, n)),
    )
    path = tmp_path / "a.dat"
    write_dat(path, ev, width=640, height=480)
    size = path.stat().st_size - 8 * n
    return path, ev, size


@pytest.mark.parametrize("how", ["zero", "huge", "flip", "random"])
def test_dat_non_monotonic_record(tmp_path: Path, how: str) -> None:
    path, ev, start = _dat(tmp_path)
    rng = np.random.default_rng(9)
    for i in rng.integers(100, 2900, 10).tolist():
        buf = bytearray(path.read_bytes())
        off = start + 8 * i
        t = int.from_bytes(buf[off : off + 4], "little")
        new = {
            "zero": 0,
            "huge": 0xFFFFFFF0,
            "flip": t ^ (1 << int(rng.integers(10, 31))),
            "random": int(rng.integers(0, 1 << 32)),
        }[how]
        buf[off : off + 4] = new.to_bytes(4, "little")
        bad = tmp_path / "bad.dat"
        bad.write_bytes(bytes(buf))
        hdr, got = read_dat(bad)
        assert got.is_time_sorted()
        dropped = hdr.skipped.get("non_monotonic_time", 0)
        assert len(got) + dropped == len(ev)
        assert_same(got[:i], ev[:i])
        assert_same(got[len(got) - (len(ev) - i - 1) :], ev[i + 1 :])
        if dropped:
            assert dropped == 1
            assert hdr.skipped_offsets == [off]
            with pytest.raises(EvtDecodeError, match="non_monotonic_time") as exc:
                read_dat(bad, strict=True)
            assert exc.value.offset == off
        else:  # the new time still fits between its neighbours
            assert int(ev.t[i - 1]) <= new <= int(ev.t[i + 1])


def test_dat_truncation_at_many_offsets(tmp_path: Path) -> None:
    path, ev, start = _dat(tmp_path)
    data = path.read_bytes()
    for cut in sorted({start, *np.random.default_rng(10).integers(start, len(data), 30).tolist()}):
        (tmp_path / "c.dat").write_bytes(data[:cut])
        hdr, got = read_dat(tmp_path / "c.dat")
        assert_same(got, ev[: (cut - start) // 8])
        assert hdr.skipped.get("truncated", 0) == (1 if (cut - start) % 8 else 0)


# ------------------------------------------------------------------ live stream


def test_live_stream_corrupt_word_costs_only_its_events() -> None:
    """The capture path (a DecodingEventSensor) decodes with the same decoder: a zeroed TIME_LOW
    in a live stream is counted as decoder_skipped_non_monotonic_time and time stays sorted."""
    data = _synthetic("evt3")
    i = _pick(_types(data, "evt3"), 6, np.random.default_rng(12), 1)[0]
    bad = _set_word(data, "evt3", i, lambda v: 0x6000)
    ref = decode_bytes(bad, "evt3")
    sensor = FixedStream(bad, 333)
    sensor.start()
    packets = sensor.read_all()
    ev = EventArray.concatenate([p.events for p in packets])
    extra = sensor.stats().extra
    sensor.close()
    assert_same(ev, ref.events)
    assert ev.is_time_sorted()
    assert extra["decoder_skipped_non_monotonic_time"] == len(decode_bytes(data, "evt3").events) - len(ev)
