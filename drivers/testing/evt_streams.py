"""What the EVT codec tests share: the real recordings (`shared/data/events` beside the checkout;
tests that need them are skipped without), synthetic encoder streams, chunked feeding and
array comparison."""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from drivers.base import Capability
from drivers.evt_stream import DecodingEventSensor, EvtBuffer
from drivers.lifecycle import END, Signal
from rigd.core.devices import DeviceInfo
from rigd.core.events import EventArray, EventPacket, TriggerEvents
from rigd.evt import Decoded, Evt3Encoder, StreamDecoder, encode, parse_raw_header

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "events"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"real Prophesee recordings not found at {DATA}")
SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
#: `@given` arguments of the tests on mutated encoder streams (`mutated`).
DIRTY = {
    "seed": st.integers(0, 2**32 - 1),
    "n_mut": st.integers(1, 40),
    "cut": st.booleans(),
    "geometry": st.sampled_from([(1280, 720), (640, 480), (1270, 715)]),
    "sizes": st.lists(st.integers(1, 500), min_size=1, max_size=4),
}


def real_body(name: str) -> bytes:
    """The event stream of a real RAW recording, its header skipped."""
    with (DATA / name).open("rb") as f:
        parse_raw_header(f)
        return f.read()


def feed_chunks(dec: StreamDecoder, data: bytes, sizes: list[int]) -> Iterator[Decoded]:
    """`dec.feed` over data cut into pieces of `sizes` (cycled), then `dec.finish()` (what words
    held back at the end decode to); what came before a strict-mode error has been yielded when
    it raises."""
    pos = i = 0
    while pos < len(data):
        k = sizes[i % len(sizes)]
        yield dec.feed(memoryview(data)[pos : pos + k])
        pos += k
        i += 1
    yield dec.finish()


class FixedStream(DecodingEventSensor[EvtBuffer]):
    """A streaming sensor handing out a fixed stream in small buffers (a camera's USB
    transfers), one a read, then nothing more: the capture path's decoding as a camera's."""

    _capabilities = frozenset({Capability.DEVICE_TIMESTAMPS})

    def __init__(self, data: bytes, size: int, fmt: str = "evt3") -> None:
        self._parts = [data[i : i + size] for i in range(0, len(data), size)]
        super().__init__(fmt, (1280, 720), buffers=len(self._parts) + 1)  # nothing dropped
        self._info = DeviceInfo(kind="event_sensor", spec="test://bytes")

    def _grab(self, timeout_s: float) -> EvtBuffer | Signal | None:
        return EvtBuffer(self._parts.pop(0), 0) if self._parts else END

    def read_all(self) -> list[EventPacket]:
        """Every packet until the stream has ended and been read."""
        packets = []
        while (p := self.read_events(10.0)) is not None:
            packets.append(p)
        return packets


def assert_same(a: EventArray | TriggerEvents, b: EventArray | TriggerEvents) -> None:
    assert len(a) == len(b)
    for name in a.__slots__:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def assert_matches_pypi_evt3(events: EventArray, name: str) -> None:
    """`events` are what the evt3 PyPI package decodes from the real recording `name`."""
    evt3_pkg = pytest.importorskip("evt3", reason="evt3 PyPI package not installed")
    ref = evt3_pkg.decode_file(str(DATA / name))
    np.testing.assert_array_equal(events.x, ref.x)
    np.testing.assert_array_equal(events.y, ref.y)
    np.testing.assert_array_equal(events.p, ref.polarity.astype(np.int8) * 2 - 1)
    np.testing.assert_array_equal(events.t, ref.timestamp.astype(np.int64))


def encoder_stream(rng: np.random.Generator, n: int, n_trig: int, loops: int, pieces: int) -> bytes:
    """Encoder output (vectors, ADDR_X, triggers) spanning `loops` 2^24 us roll-overs, encoded in
    `pieces` calls of one streaming encoder."""
    span = (loops + 1) * (1 << 24) + int(rng.integers(1, 1 << 24))
    t = np.sort(rng.integers(0, span, n))
    burst = rng.random(n) < 0.6
    t = np.maximum.accumulate(np.where(burst, np.r_[t[:1], t[:-1]], t))
    same = burst & (np.r_[-1, t[:-1]] == t)
    y = np.where(same, np.r_[0, rng.integers(0, 720, n)[:-1]], rng.integers(0, 720, n))
    # x clustered near both edges too, so vectors reach past the width (fallback) now and then
    x = np.where(rng.random(n) < 0.2, rng.integers(1260, 1280, n), rng.integers(0, 1280, n))
    x = np.where(same, np.minimum(np.r_[0, x[:-1]] + rng.integers(1, 14, n), 1279), x)
    ev = EventArray.from_arrays(x, y, rng.integers(0, 2, n), t)
    order = np.lexsort((ev.x, ev.p, ev.y, ev.t))
    ev = ev[order]
    tt = np.sort(rng.integers(0, span, n_trig)).astype(np.int64)
    tr = TriggerEvents(
        tt, rng.integers(0, 2, n_trig).astype(np.uint8), rng.integers(0, 16, n_trig).astype(np.uint8)
    )
    enc = Evt3Encoder()
    cuts = np.linspace(0, span, pieces + 1).astype(np.int64)
    out = []
    for lo, hi in itertools.pairwise(cuts):
        last = hi == cuts[-1]
        e = ev[(ev.t >= lo) & ((ev.t < hi) | last)]
        r = tr[(tr.t >= lo) & ((tr.t < hi) | last)]
        out.append(enc.encode(e, r))
    return b"".join(out)


def mutated(rng: np.random.Generator, data: bytes, n_mut: int, *, cut: bool) -> bytes:
    """`data`'s words with `n_mut` of them broken: random words, random types on kept payloads, or
    bit flips; `cut`: from a random word on (a stream joined mid-way)."""
    buf = np.frombuffer(data, "<u2").copy()
    if buf.size:
        idx = rng.integers(0, buf.size, n_mut)
        kind = rng.integers(0, 4, n_mut)
        rand = rng.integers(0, 1 << 16, n_mut)
        buf[idx] = np.where(
            kind == 0,
            rand,
            np.where(kind == 1, (rand & 0xF000) | (buf[idx] & 0xFFF), buf[idx] ^ (1 << (rand % 16))),
        )
        if cut:
            buf = buf[int(rng.integers(0, buf.size)) :]
    return buf.tobytes()


# -- streams that jump back in time (two recordings joined) ---------------------------------
FORMATS = ("evt3", "evt2", "evt21", "evt21_le")
WORD = {"evt3": 2, "evt2": 4, "evt21": 8, "evt21_le": 8}
SHIFT = {"evt3": 12, "evt2": 6, "evt21": 6, "evt21_le": 6}  # TIME_HIGH period: 1 << SHIFT us


def time_highs(data: bytes, fmt: str) -> tuple[np.ndarray, np.ndarray]:
    """Word indices and values of the TIME_HIGH words."""
    if fmt == "evt3":
        w = np.frombuffer(data, "<u2", len(data) // 2).astype(np.int64)
        idx = np.flatnonzero(w >> 12 == 8)
        return idx, w[idx] & 0xFFF
    u32 = np.frombuffer(data, "<u4", len(data) // 4).astype(np.int64)
    half = {"evt2": u32, "evt21": u32[0::2], "evt21_le": u32[1::2]}[fmt]
    idx = np.flatnonzero(half >> 28 == 8)
    return idx, half[idx] & 0xFFFFFFF


def segment(fmt: str, rng: np.random.Generator, t0: int, periods: int, per_period: int) -> bytes:
    """An encoded stream starting at its own base t0 (no TIME_HIGH words before it, as a sensor
    re-based there sends): events and a few trigger edges over `periods` TIME_HIGH periods."""
    span = periods << SHIFT[fmt]
    n = max(1, periods * per_period)
    t = np.sort(np.r_[t0, rng.integers(t0, t0 + span, n - 1)]).astype(np.int64)
    ev = EventArray.from_arrays(rng.integers(0, 1280, n), rng.integers(0, 720, n), rng.integers(0, 2, n), t)
    ev = ev[np.lexsort((ev.x, ev.p, ev.y, ev.t))]
    k = int(rng.integers(0, 4))
    tt = np.sort(rng.integers(t0, t0 + span, k)).astype(np.int64)
    tr = TriggerEvents(tt, rng.integers(0, 2, k).astype(np.uint8), np.zeros(k, np.uint8))
    data = encode(fmt, ev, tr)
    idx, val = time_highs(data, fmt)
    mask = 0xFFF if fmt == "evt3" else 0xFFFFFFF
    first = int(idx[int(np.flatnonzero(val == (t0 >> SHIFT[fmt]) & mask)[0])])
    return data[first * WORD[fmt] :]


def joined(fmt: str, seed: int, jump_periods: int = 30) -> tuple[bytes, bytes, bytes]:
    """Two segments, the second based `jump_periods` TIME_HIGH periods before the first ends:
    (first, second, both joined)."""
    rng = np.random.default_rng(seed)
    s = SHIFT[fmt]
    a = segment(fmt, rng, 1000 << s, 50, 4)
    b = segment(fmt, rng, (1050 - jump_periods) << s, 50, 4)
    return a, b, a + b
