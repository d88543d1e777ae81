"""EVT codec: real recordings, round trips, chunking invariance and hostile input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.testing.evt_streams import (
    DATA,
    SETTINGS,
    assert_matches_pypi_evt3,
    assert_same,
    feed_chunks,
    needs_data,
    real_body,
)
from rigd.core.events import EventArray, TriggerEvents
from rigd.evt import (
    Decoded,
    Evt3Encoder,
    EvtDecodeError,
    RawHeader,
    RawReader,
    StreamDecoder,
    decode_bytes,
    encode,
    encode_evt2,
    encode_evt3,
    read_dat,
    read_raw,
    write_dat,
    write_raw,
)

# file, events, first t, last t (../shared/data/README.md, OpenEB semantics)
REAL = [
    ("evt3_gen41_sample.raw", "evt3", 1280, 720, 219_596, 11_718_656, 11_727_457),
    ("evt3_pedestrians.raw", "evt3", 1280, 720, 5_000, 5_840_504, 5_885_714),
    ("evt2_gen3_sample.raw", "evt2", 640, 480, 539_481, 1_317_888, 1_367_888),
]


def _random_stream(
    rng: np.random.Generator, n: int, n_trig: int, t_span: int, width: int = 1280, height: int = 720
) -> tuple[EventArray, TriggerEvents]:
    """Sorted events with bursts (same t, same row) so vectors are exercised, plus triggers."""
    if n == 0:
        return EventArray.empty(), TriggerEvents.empty() if n_trig == 0 else _random_stream(
            rng, 1, n_trig, t_span, width, height
        )[1]
    t = np.sort(rng.integers(0, t_span, n))
    burst = rng.random(n) < 0.5
    t = np.maximum.accumulate(np.where(burst, np.r_[t[:1], t[:-1]], t))
    y = np.where(burst, np.r_[0, rng.integers(0, height, n - 1)], rng.integers(0, height, n))
    y = np.where(burst & (np.r_[-1, t[:-1]] == t), np.r_[0, y[:-1]], y)
    x = rng.integers(0, width, n)
    p = rng.integers(0, 2, n)
    ev = EventArray.from_arrays(x, y, p, t)
    tt = np.sort(rng.integers(0, t_span, n_trig)).astype(np.int64)
    tr = TriggerEvents(
        tt, rng.integers(0, 2, n_trig).astype(np.uint8), rng.integers(0, 16, n_trig).astype(np.uint8)
    )
    return ev, tr


# ------------------------------------------------------------------ real files


@needs_data
@pytest.mark.parametrize(("name", "fmt", "w", "h", "count", "t0", "t1"), REAL)
def test_real_files_decode_to_readme(
    name: str, fmt: str, w: int, h: int, count: int, t0: int, t1: int
) -> None:
    hdr, dec = read_raw(DATA / name, strict=True)
    assert (hdr.fmt, hdr.width, hdr.height) == (fmt, w, h)
    ev = dec.events
    assert len(ev) == count
    assert (int(ev.t[0]), int(ev.t[-1])) == (t0, t1)
    assert ev.is_time_sorted()
    # constant-memory reader with odd chunk sizes gives the same events
    reader = RawReader(DATA / name, chunk_bytes=4093)
    assert_same(EventArray.concatenate([d.events for d in reader]), ev)
    assert not any(reader.stats.values())


@needs_data
def test_dat_file() -> None:
    hdr, ev = read_dat(DATA / "dat_ncars_sample.dat")
    assert len(ev) == 4407
    assert hdr.event_size == 8
    assert ev.is_time_sorted()


@needs_data
@pytest.mark.parametrize("name", ["evt3_gen41_sample.raw", "evt3_pedestrians.raw"])
def test_evt3_matches_pypi_evt3(name: str) -> None:
    assert_matches_pypi_evt3(read_raw(DATA / name)[1].events, name)


@pytest.mark.slow
@needs_data
def test_raw_write_read_round_trip(tmp_path: Path) -> None:
    _, dec = read_raw(DATA / "evt3_pedestrians.raw")
    for fmt in ("evt3", "evt2", "evt21", "evt21_le"):
        out = tmp_path / f"x_{fmt}.raw"
        write_raw(out, RawHeader(fmt=fmt, width=1280, height=720, fields={"serial_number": "42"}), dec.events)
        hdr2, dec2 = read_raw(out, strict=True)
        assert (hdr2.fmt, hdr2.width, hdr2.height, hdr2.serial_number) == (fmt, 1280, 720, "42")
        assert_same(dec2.events, dec.events)


def test_dat_round_trip(tmp_path: Path) -> None:
    ev, _ = _random_stream(np.random.default_rng(1), 500, 0, 10_000_000)
    write_dat(tmp_path / "a.dat", ev, width=1280, height=720)
    hdr, back = read_dat(tmp_path / "a.dat")
    assert (hdr.width, hdr.height) == (1280, 720)
    assert_same(back, ev)


# ------------------------------------------------------------------ properties


@SETTINGS
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(0, 400),
    n_trig=st.integers(0, 20),
    loops=st.integers(0, 5),
    fmt=st.sampled_from(["evt3", "evt2", "evt21", "evt21_le"]),
)
def test_encode_decode_identity(seed: int, n: int, n_trig: int, loops: int, fmt: str) -> None:
    """Includes timestamps spanning several 2^24 us EVT3 roll-overs (and EVT2's 34-bit one)."""
    rng = np.random.default_rng(seed)
    span = (loops + 1) * (1 << 24) + int(rng.integers(1, 1 << 24))
    if fmt != "evt3" and rng.random() < 0.3:
        span = 3 * (1 << 34)
    ev, tr = _random_stream(rng, n, n_trig, span)
    tr = TriggerEvents(tr.t, tr.p, tr.channel & (0xF if fmt == "evt3" else 0x1F))
    data = encode(fmt, ev, tr)
    dec = decode_bytes(data, fmt, strict=True)
    assert_same(dec.events, ev)
    assert_same(dec.triggers, tr)


@SETTINGS
@given(seed=st.integers(0, 2**32 - 1), splits=st.integers(1, 6))
def test_streaming_encoder_equals_one_shot(seed: int, splits: int) -> None:
    rng = np.random.default_rng(seed)
    ev, tr = _random_stream(rng, 300, 10, 1 << 26)
    cuts = np.sort(rng.integers(0, 300, splits))
    enc = Evt3Encoder()
    parts = []
    lo = 0
    for c in [*cuts.tolist(), 300]:
        hi_t = int(ev.t[c - 1]) if c > 0 else -1
        tlo = int(np.searchsorted(tr.t, int(ev.t[lo - 1]) if lo > 0 else -1, "right"))
        thi = int(np.searchsorted(tr.t, hi_t, "right")) if c < 300 else len(tr)
        parts.append(enc.encode(ev[lo:c], tr[tlo:thi]))
        lo = c
    dec = decode_bytes(b"".join(parts), "evt3", strict=True)
    assert_same(dec.events, ev)
    assert_same(dec.triggers, tr)


def _chunked(data: bytes, fmt: str, sizes: list[int]) -> tuple[EventArray, TriggerEvents]:
    out = Decoded.concatenate(list(feed_chunks(StreamDecoder(fmt), data, sizes)))
    return out.events, out.triggers


@pytest.mark.parametrize("fmt", ["evt3", "evt2", "evt21", "evt21_le"])
def test_every_chunk_size_equals_whole(fmt: str) -> None:
    ev, tr = _random_stream(np.random.default_rng(7), 120, 6, 3 << 24)
    data = encode(fmt, ev, TriggerEvents(tr.t, tr.p, tr.channel & 0xF))
    whole = decode_bytes(data, fmt, strict=True)
    for size in range(1, 65):
        e, t = _chunked(data, fmt, [size])
        assert_same(e, whole.events)
        assert_same(t, whole.triggers)


@needs_data
@SETTINGS
@given(seed=st.integers(0, 2**32 - 1))
def test_random_chunking_of_real_file(seed: int) -> None:
    body = real_body("evt3_gen41_sample.raw")
    rng = np.random.default_rng(seed)
    sizes = rng.integers(1, 20_000, 50).tolist()
    e, _ = _chunked(body, "evt3", sizes)
    assert_same(e, decode_bytes(body, "evt3").events)


# ------------------------------------------------------------------ hostile input


def test_truncated_stream() -> None:
    data = encode_evt3(*_random_stream(np.random.default_rng(3), 50, 2, 1 << 20))[:-1]
    dec = StreamDecoder("evt3")
    dec.feed(data)
    dec.finish()
    assert dec.stats["truncated"] == 1
    strict = StreamDecoder("evt3", strict=True)
    strict.feed(data)
    with pytest.raises(EvtDecodeError) as exc:
        strict.finish()
    assert exc.value.kind == "truncated"
    assert exc.value.offset == len(data) - 1


def _words(*ws: int) -> bytes:
    return np.array(ws, "<u2").tobytes()


def test_non_monotonic_time_high() -> None:
    # TH 100, event, TH 90 (small fall: violation, skipped), event, TH 3000, TH 5 (roll-over)
    data = _words(0x8064, 0x0005, 0x2007, 0x805A, 0x2008, 0x8BB8, 0x8005, 0x2009)
    dec = decode_bytes(data, "evt3")
    np.testing.assert_array_equal(dec.events.t, [100 << 12, 100 << 12, (1 << 24) | (5 << 12)])
    sd = StreamDecoder("evt3")
    sd.feed(data)
    assert sd.stats["non_monotonic_time_high"] == 1
    with pytest.raises(EvtDecodeError, match="non_monotonic_time_high at byte offset 6") as exc:
        decode_bytes(data, "evt3", strict=True)
    assert exc.value.offset == 6


def test_vector_without_base_and_event_without_y() -> None:
    data = _words(0x8001, 0x4FFF, 0x2003, 0x0002, 0x3010, 0x4003)
    sd = StreamDecoder("evt3")
    out = sd.feed(data)
    assert sd.stats["vector_without_base"] == 1
    assert sd.stats["event_without_y"] == 1
    np.testing.assert_array_equal(out.events.x, [16, 17])
    with pytest.raises(EvtDecodeError, match="vector_without_base at byte offset 2"):
        decode_bytes(data, "evt3", strict=True)


def test_header_lying_about_geometry(tmp_path: Path) -> None:
    ev = EventArray.from_arrays([10, 1000, 1279], [5, 600, 719], [1, 0, 1], [1, 2, 3])
    path = tmp_path / "lie.raw"
    path.write_bytes(RawHeader(fmt="evt3", width=640, height=480).to_bytes() + encode_evt3(ev))
    hdr, dec = read_raw(path)
    assert len(dec.events) == 1
    reader = RawReader(path)
    list(reader)
    assert reader.stats["out_of_range_xy"] == 2
    with pytest.raises(EvtDecodeError, match="out_of_range_xy at byte offset") as exc:
        read_raw(path, strict=True)
    assert exc.value.offset > hdr.size


def test_unknown_type_evt2() -> None:
    data = np.array([0x80000001, 0x30000000, 0x10000000 | (5 << 11) | 6], "<u4").tobytes()
    sd = StreamDecoder("evt2")
    assert len(sd.feed(data).events) == 1
    assert sd.stats["unknown_type"] == 1
    with pytest.raises(EvtDecodeError, match="unknown_type at byte offset 4"):
        decode_bytes(data, "evt2", strict=True)


#: Inputs each format's fuzz decodes (random bytes, and mutated and cut encodings).
FUZZ_INPUTS = 300


@pytest.mark.slow
@pytest.mark.timeout(120)
@pytest.mark.parametrize("fmt", ["evt3", "evt2", "evt21", "evt21_le"])
def test_fuzz_random_and_mutated(fmt: str) -> None:
    """Fuzz with a fixed number of inputs (not a time budget: on a cold numba cache the first decode
    compiles): tolerant never raises, strict raises only EvtDecodeError, output sane."""
    rng = np.random.default_rng(11)
    ev, tr = _random_stream(rng, 3000, 20, 1 << 26)
    seed = encode(fmt, ev, TriggerEvents(tr.t, tr.p, tr.channel & 0xF))
    bodies = [seed]
    if DATA.is_dir():
        bodies.append(
            real_body("evt3_gen41_sample.raw" if fmt == "evt3" else "evt2_gen3_sample.raw")[:40_000]
        )
    for i in range(1, FUZZ_INPUTS + 1):
        if i % 3 == 0:
            data = rng.integers(0, 256, int(rng.integers(0, 5000)), dtype=np.uint8).tobytes()
        else:
            buf = bytearray(bodies[i % len(bodies)])
            for _ in range(int(rng.integers(1, 30))):
                buf[int(rng.integers(0, len(buf)))] = int(rng.integers(0, 256))
            cut = int(rng.integers(0, len(buf) + 1))
            data = bytes(buf[: cut if i % 5 == 0 else len(buf)])
        out = decode_bytes(data, fmt, width=640, height=480)
        e = out.events
        assert len(e) <= len(data) * 6
        assert e.x.size == 0 or (int(e.x.max()) < 640 and int(e.y.max()) < 480)
        # time never runs back: what a corrupt word would take back is dropped and counted
        assert (np.diff(e.t) >= 0).all()
        assert (np.diff(out.triggers.t) >= 0).all()
        try:
            decode_bytes(data, fmt, width=640, height=480, strict=True)
        except EvtDecodeError as err:
            offset = err.offset
            assert 0 <= offset <= len(data)


def test_encoder_rejects_unsorted_and_backwards() -> None:
    from rigd.core.errors import EventDataError

    ev = EventArray.from_arrays([1, 2], [1, 1], [1, 1], [10, 5])
    with pytest.raises(EventDataError):
        encode_evt3(ev)
    enc = Evt3Encoder()
    enc.encode(EventArray.from_arrays([1], [1], [1], [100]))
    with pytest.raises(EventDataError):
        enc.encode(EventArray.from_arrays([1], [1], [1], [50]))
    with pytest.raises(EventDataError):
        encode_evt2(EventArray.from_arrays([3000], [1], [1], [1]))
