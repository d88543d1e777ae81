"""Time-window reads (`take.sensor(name).events(t0, t1)`) against a brute-force mask over all events,
for several event chunk sizes, the old default (262 144) among them: windows across chunk
boundaries, on ms-index edges, before `t_offset`, past the ends, empty and reversed."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.events import EventArray
from rigd.core.schema import SyncReport
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.take import Take, TakeWriter, open_take
from rigd.take.seal import finalize_take

W, H = 96, 64
N_EVENTS = 600_000
MAP = ClockMap(device_ref_us=100_000, rig_ref_us=7_000_000, rate=1.00004, frac_us=0.3)
CHUNKS = (1024, 4096, 32768, 1 << 18)


def make_events(n: int, seed: int = 0) -> EventArray:
    """Dense runs of equal and close timestamps, with a few gaps of many empty milliseconds."""
    rng = np.random.default_rng(seed)
    dt = rng.choice(np.array([0, 0, 1, 2, 3, 5], np.int64), n)
    gaps = rng.random(n) < 2e-5
    dt[gaps] = rng.integers(3_000, 40_000, int(gaps.sum()))
    t = 100_000 + np.cumsum(dt)
    return EventArray.from_arrays(rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, 2, n), t)


@dataclass
class Written:
    path: Path
    chunk: int
    t: np.ndarray
    """All rig times, as the reader returns them."""


def write(path: Path, chunk: int) -> Written:
    ev = make_events(N_EVENTS)
    cfg = WriterConfig(event_chunk=chunk, event_compression="lz4", fsync=False)
    w = TakeWriter(path, rig_config_json="{}", take_id=path.stem, config=cfg, rigd_version="t")
    w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="sim://t/ev0"), W, H, "{}")
    step = 70_001  # appends and flushes that do not line up with chunks
    for a in range(0, N_EVENTS, step):
        w.append_events("ev0", ev[a : a + step])
        w.flush()
    rig = MAP.to_rig(ev.t)
    first_pulse = int(rig[N_EVENTS // 3])  # events before it get negative stored t
    w.append_pulses(PulseBatch(np.zeros(1, np.int64), np.array([first_pulse]), np.zeros(1, np.int64)))
    report = SyncReport(rate_hz=30.0, n_pulses=1, t_first_pulse_us=first_pulse, t_last_pulse_us=first_pulse)
    finalize_take(w, {"ev0": MAP}, {}, report)
    w.close()
    return Written(path, chunk, rig)


@pytest.fixture(scope="module", params=CHUNKS, ids=lambda c: f"chunk{c}")
def written(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Written:
    chunk = int(request.param)
    return write(tmp_path_factory.mktemp("windows") / f"take-{chunk}.h5", chunk)


def brute(take: Take, t0: int, t1: int) -> EventArray:
    ev = take.sensor("ev0").events()
    return ev[np.flatnonzero((ev.t >= t0) & (ev.t < t1))]


def assert_same(got: EventArray, want: EventArray) -> None:
    for k in "xypt":
        np.testing.assert_array_equal(getattr(got, k), getattr(want, k), err_msg=k)
        assert getattr(got, k).dtype == getattr(want, k).dtype, k


def edges(w: Written) -> list[int]:
    """Times where a window bound is most likely wrong: chunk boundaries, millisecond edges of
    `ms_to_idx` (relative to t_offset), t_offset itself, the first and last event."""
    t = w.t
    with open_take(w.path) as take:
        off = int(take._f["events/ev0/t_offset"][()])
    at = [int(t[i]) for i in range(0, t.size, w.chunk)] + [int(t[0]), int(t[-1]), off]
    ms = [off + 1000 * k for k in range(int((t[0] - off) // 1000) - 1, int((t[-1] - off) // 1000) + 2, 97)]
    return sorted({v + d for v in at + ms for d in (-1, 0, 1)})


def test_layout_uses_the_chunk(written: Written) -> None:
    with open_take(written.path) as take:
        assert take._f["events/ev0/t"].chunks == (written.chunk,)
        assert take.sensor("ev0").count == N_EVENTS
        np.testing.assert_array_equal(take.sensor("ev0").events().t, written.t)


@pytest.mark.slow
def test_windows_on_chunk_and_ms_edges(written: Written) -> None:
    cand = edges(written)
    rng = np.random.default_rng(1)
    with open_take(written.path) as take:
        for t0 in rng.choice(cand, min(60, len(cand)), replace=False):
            for length in (0, 1, 999, 1000, 1001, 50_000, 400_000):
                assert_same(
                    take.sensor("ev0").events(int(t0), int(t0) + length),
                    brute(take, int(t0), int(t0) + length),
                )


def test_whole_and_outside(written: Written) -> None:
    t = written.t
    with open_take(written.path) as take:
        assert len(take.sensor("ev0").events(int(t[0]) - 10**9, int(t[-1]) + 10**9)) == N_EVENTS
        assert len(take.sensor("ev0").events(int(t[-1]) + 1, int(t[-1]) + 50_000)) == 0
        assert len(take.sensor("ev0").events(int(t[0]) - 50_000, int(t[0]))) == 0
        assert len(take.sensor("ev0").events(int(t[N_EVENTS // 2]), int(t[100]))) == 0  # reversed: empty
        assert take.sensor("ev0").index(int(t[N_EVENTS // 2])) == int(np.searchsorted(t, t[N_EVENTS // 2]))


def test_iter_events_matches(written: Written) -> None:
    t = written.t
    with open_take(written.path) as take:
        got = np.concatenate([w.t for w in take.sensor("ev0").iter(50_000)])
        np.testing.assert_array_equal(got, t)


@pytest.mark.slow
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_random_windows_match_brute_force(written: Written, data: st.DataObject) -> None:
    t = written.t
    lo, hi = int(t[0]) - 5_000, int(t[-1]) + 5_000
    cand = edges(written)
    t0 = data.draw(st.one_of(st.integers(lo, hi), st.sampled_from(cand)), "t0")
    length = data.draw(st.one_of(st.integers(-2_000, 120_000), st.sampled_from([0, 1, 1000, 50_000])), "len")
    with open_take(written.path) as take:
        assert_same(take.sensor("ev0").events(t0, t0 + length), brute(take, t0, t0 + length))
