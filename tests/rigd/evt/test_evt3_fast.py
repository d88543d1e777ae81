"""The fast EVT 3.0 kernel (evt3_fast) is indistinguishable from the reference state machine."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.testing.evt_streams import (
    DIRTY,
    SETTINGS,
    assert_matches_pypi_evt3,
    assert_same,
    encoder_stream,
    feed_chunks,
    mutated,
    needs_data,
    real_body,
)
from rigd.core.events import EventArray, TriggerEvents
from rigd.evt import Decoded, EvtDecodeError, StreamDecoder, evt3, evt3_fast, raw
from rigd.evt.errors import STATS_SIZE
from rigd.evt.kernels import decode_config
from rigd.evt.raw import _Out

KERNELS = {"ref": evt3.decode_kernel, "fast": evt3_fast.decode_kernel}

Result = tuple[EventArray, TriggerEvents, dict[str, int], tuple[int, str] | None, list[int]]


def _decode(
    data: bytes,
    kernel: str,
    sizes: list[int] | None = None,
    *,
    strict: bool = False,
    w: int = 1280,
    h: int = 720,
) -> Result:
    """Decode through StreamDecoder with the chosen kernel; chunked when `sizes` is given."""
    dec = StreamDecoder("evt3", width=w, height=h, strict=strict)
    dec._kernel = KERNELS[kernel]
    parts: list[Decoded] = []
    error = None
    try:
        for part in feed_chunks(dec, data, sizes or [max(1, len(data))]):
            parts.append(part)  # kept when a later chunk raises
    except EvtDecodeError as exc:
        error = (exc.offset, exc.kind)
    ev = EventArray.concatenate([d.events for d in parts]) if parts else EventArray.empty()
    tr = TriggerEvents.concatenate([d.triggers for d in parts]) if parts else TriggerEvents.empty()
    return ev, tr, dec.stats, error, dec._state.tolist()


def _assert_same(a: Result, b: Result) -> None:
    assert_same(a[0], b[0])
    assert_same(a[1], b[1])
    assert a[2] == b[2]  # skip counts by kind
    assert a[3] == b[3]  # strict: offset and kind of the error
    assert a[4] == b[4]  # outgoing decoder state


# ------------------------------------------------------------------ production wiring


def test_production_path_uses_fast_kernel() -> None:
    assert raw.USE_EVT3_FAST
    assert StreamDecoder("evt3")._kernel is evt3_fast.decode_kernel


# ------------------------------------------------------------------ real files


@pytest.mark.slow
@needs_data
@pytest.mark.parametrize("name", ["evt3_gen41_sample.raw", "evt3_pedestrians.raw"])
def test_real_files(name: str) -> None:
    body = real_body(name)
    ref = _decode(body, "ref")
    _assert_same(_decode(body, "fast"), ref)
    for sizes in ([1], [3, 4097, 7], [65536]):
        _assert_same(
            _decode(body[:200_000] if sizes == [1] else body, "fast", sizes),
            _decode(body[:200_000] if sizes == [1] else body, "ref"),
        )
    # a smaller geometry turns part of the file into out-of-range events: fallback path
    _assert_same(_decode(body, "fast", w=640, h=480), _decode(body, "ref", w=640, h=480))
    _assert_same(
        _decode(body, "fast", w=640, h=480, strict=True), _decode(body, "ref", w=640, h=480, strict=True)
    )


@needs_data
@pytest.mark.parametrize("name", ["evt3_gen41_sample.raw", "evt3_pedestrians.raw"])
def test_real_files_match_pypi_evt3(name: str) -> None:
    assert_matches_pypi_evt3(_decode(real_body(name), "fast")[0], name)


# ------------------------------------------------------------------ encoder streams


@SETTINGS
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(0, 600),
    n_trig=st.integers(0, 20),
    loops=st.integers(0, 4),
    pieces=st.integers(1, 4),
    sizes=st.lists(st.integers(1, 300), min_size=1, max_size=6),
)
@pytest.mark.slow
def test_encoder_streams(seed: int, n: int, n_trig: int, loops: int, pieces: int, sizes: list[int]) -> None:
    data = encoder_stream(np.random.default_rng(seed), n, n_trig, loops, pieces)
    ref = _decode(data, "ref", strict=True)
    assert ref[3] is None
    _assert_same(_decode(data, "fast", strict=True), ref)
    _assert_same(_decode(data, "fast", sizes, strict=True), ref)
    _assert_same(_decode(data, "fast", sizes), _decode(data, "ref", sizes))


# ------------------------------------------------------------------ dirty input


@pytest.mark.slow
@SETTINGS
@given(**DIRTY)
def test_dirty_input_falls_back(
    seed: int, n_mut: int, cut: bool, geometry: tuple[int, int], sizes: list[int]
) -> None:
    """Mutated words (unknown types, small TIME_HIGH falls, bad x/y, vectors without base, words
    before the first TIME_HIGH): tolerant skip counts, strict error offsets and events unchanged."""
    rng = np.random.default_rng(seed)
    data = mutated(rng, encoder_stream(rng, 400, 5, 2, 2), n_mut, cut=cut)
    w, h = geometry
    for strict in (False, True):
        ref = _decode(data, "ref", strict=strict, w=w, h=h)
        _assert_same(_decode(data, "fast", strict=strict, w=w, h=h), ref)
        _assert_same(
            _decode(data, "fast", sizes, strict=strict, w=w, h=h),
            _decode(data, "ref", sizes, strict=strict, w=w, h=h),
        )


def test_hand_made_violations() -> None:
    words = [
        0x6001, 0x0005, 0x2007,  # before TIME_HIGH
        0x8064, 0x4FFF, 0x2003,  # vector without base, event without y
        0x0002, 0x3010, 0x4003, 0x2900,  # ok vector; x 0x100 beyond a 200-wide sensor
        0x805A, 0x2008,  # small TIME_HIGH fall
        0x1234, 0x9000, 0xB000,  # unknown types
        0x7000, 0xE000, 0xF000,  # ignored types
        0x03FF, 0x2001, 0x0003, 0x30BE, 0x4FFF,  # y beyond height; vector reaching past width
        0xA301, 0x8BB8, 0x8005, 0x2009,  # trigger, roll-over
    ]  # fmt: skip
    data = np.array(words, "<u2").tobytes()
    for strict in (False, True):
        for sizes in (None, [1], [3], [5]):
            ref = _decode(data, "ref", sizes, strict=strict, w=200, h=100)
            _assert_same(_decode(data, "fast", sizes, strict=strict, w=200, h=100), ref)
    assert sum(_decode(data, "ref", w=200, h=100)[2].values()) > 5


# ------------------------------------------------------------------ output capacity


def _run_small(data: bytes, kernel: Callable[..., tuple[int, int, int, int]]) -> tuple[Any, ...]:
    """StreamDecoder's growth loop with tiny initial outputs: the kernel stops when nearly full."""
    words = np.frombuffer(data, "<u2")
    out = _Out(13, 1)
    stt = evt3.new_decoder_state()
    stats = np.zeros(STATS_SIZE, np.int64)
    pos = 0
    calls = 0
    cfg = decode_config(1280, 720, False)
    while pos < words.size:
        pos, out.n, out.nt, err = kernel(words, pos, words.size, stt, out.arrays, out.n, out.nt, stats, cfg)
        assert err == 0
        calls += 1
        out.grow(12)
    r = out.result()
    return r.events.x, r.events.y, r.events.p, r.events.t, r.triggers.t, r.triggers.channel, stt, stats


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_growing_outputs(seed: int) -> None:
    data = encoder_stream(np.random.default_rng(seed), 3000, 200, 2, 3)
    a = _run_small(data, evt3.decode_kernel)
    b = _run_small(data, evt3_fast.decode_kernel)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_vector_base_runs(seed: int) -> None:
    """Runs of (VECT_BASE_X, vector) pairs, decoded by the fast kernel's pair loop: bases near and
    past the width, both polarities, bases without a vector, pairs cut by chunks and by output
    capacity, and the polarity/base state carried out of the loop."""
    rng = np.random.default_rng(seed)
    words = [0x8010, 0x0005]
    for _ in range(3000):
        r = rng.random()
        if r < 0.7:
            base = int(rng.integers(150, 200)) if rng.random() < 0.2 else int(rng.integers(0, 150))
            words.append(0x3000 | (int(rng.integers(0, 2)) << 11) | base)
            k = rng.random()
            if k < 0.45:
                words.append(0x4000 | (1 << int(rng.integers(0, 12))))
            elif k < 0.6:
                words.append(0x4000 | int(rng.integers(0, 1 << 12)))
            elif k < 0.8:
                words.append(0x5000 | int(rng.integers(0, 1 << 8)))
        elif r < 0.8:
            words.append(0x4000 | int(rng.integers(0, 1 << 12)))
        elif r < 0.9:
            words.append(0x2000 | (int(rng.integers(0, 2)) << 11) | int(rng.integers(0, 200)))
        else:
            words.append(0x0000 | int(rng.integers(0, 100)))
    _assert_fast_matches_reference(words)


def _assert_fast_matches_reference(words: list[int]) -> None:
    """The fast kernel decodes `words` (a 200x100 sensor) exactly as the reference does: strict
    and tolerant, cut into chunks of every size given, and at a small output capacity (words
    with a vector base past the width left out there)."""
    data = np.array(words, "<u2").tobytes()
    for strict in (False, True):
        for sizes in (None, [1], [3], [2, 5], [77]):
            ref = _decode(data, "ref", sizes, strict=strict, w=200, h=100)
            _assert_same(_decode(data, "fast", sizes, strict=strict, w=200, h=100), ref)
    valid = np.array([w for w in words if not (w >> 12 == 3 and (w & 0x7FF) >= 150)], "<u2").tobytes()
    a = _run_small(valid, evt3.decode_kernel)
    b = _run_small(valid, evt3_fast.decode_kernel)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)


def _gen4_words(rng: np.random.Generator, n: int) -> list[int]:
    """Words shaped like a Gen4's: ADDR_Y with single ADDR_X under it, TIME_LOW steps, repeated
    TIME_HIGHs each followed by a TIME_LOW (higher, equal or lower than the time before it) or by
    another word, and (VECT_BASE_X, VECT_12, VECT_12, VECT_8) groups with 0 to 32 pixels, bases
    near and past the width, and groups cut short or out of order."""
    words = [0x8010, 0x6000, 0x0005]
    th, tl = 0x10, 0
    for _ in range(n):
        r = rng.random()
        if r < 0.5:
            words.append(0x2000 | (int(rng.integers(0, 2)) << 11) | int(rng.integers(0, 200)))
        elif r < 0.62:
            words.append(int(rng.integers(0, 100)))
        elif r < 0.7:
            tl = min(0xFFF, tl + int(rng.integers(0, 40)))
            words.append(0x6000 | tl)
        elif r < 0.78:
            words.append(0x8000 | th)  # a repeat
            k = rng.random()
            if k < 0.6:
                tl = min(0xFFF, tl + int(rng.integers(0, 3)))
                words.append(0x6000 | tl)
            elif k < 0.8:
                tl = int(rng.integers(0, tl + 1))  # lower: time goes back
                words.append(0x6000 | tl)
            elif k < 0.9:
                tl = 0  # the repeat's own reset, then events at it
            else:
                th, tl = (th + 1) & 0xFFF, 0
                words.append(0x8000 | th)
        else:
            base = int(rng.integers(160, 200)) if rng.random() < 0.2 else 32 * int(rng.integers(0, 5))
            words.append(0x3000 | (int(rng.integers(0, 2)) << 11) | base)
            bits = int(rng.integers(0, 2**32)) & int(rng.integers(0, 2**32)) & int(rng.integers(0, 2**32))
            group = [0x4000 | (bits & 0xFFF), 0x4000 | ((bits >> 12) & 0xFFF), 0x5000 | (bits >> 24)]
            k = rng.random()
            if k < 0.1:
                group = group[: int(rng.integers(0, 3))]
            elif k < 0.15:
                group = [group[0], group[2], group[1]]
            words += group
    return words


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_gen4_shaped_streams(seed: int) -> None:
    """The fast kernel's Gen4 paths (the vector group as one mask, a repeated TIME_HIGH taken on
    with its TIME_LOW) decode exactly what the reference does, cut anywhere and at any capacity."""
    words = _gen4_words(np.random.default_rng(seed), 4000)
    _assert_fast_matches_reference(words)


def test_output_sizing_dense_and_sparse() -> None:
    """Outputs are first sized for one event a word: a stream of full vectors (12 events a word)
    grows them and decodes as the reference does; a sparse one (time words, a few events) gets
    its events copied out of the reserve rather than a slice that keeps it."""
    dense = [0x8001, 0x6000, 0x0007] + [0x3000, 0x4FFF, 0x4FFF, 0x5FFF] * 2000
    data = np.array(dense, "<u2").tobytes()
    ref = _decode(data, "ref")
    assert len(ref[0]) == 2000 * 32
    for sizes in (None, [4096], [3, 5000]):
        _assert_same(_decode(data, "fast", sizes), ref)
    sparse = [0x8001] + [0x6000 | i for i in range(4000)] + [0x0007, 0x2005]
    dec = StreamDecoder("evt3").feed(np.array(sparse, "<u2").tobytes())
    assert len(dec.events) == 1
    assert dec.events.t.base is None or dec.events.t.base.shape[0] < 100
