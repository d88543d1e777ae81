"""`take.sensor(name)`: one event sensor's EventSeries, on takes written by the real writer.

Unknown names, window edges and empty windows, a sensor without events, a take never
finalized, and the window reader `events(t0, t1)` against DSEC's EventSlicer algorithm on the
same file.
"""

from __future__ import annotations

import itertools
import re
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import pytest

from drivers.testing.evt_packets import packets_of
from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.errors import TakeError
from rigd.core.events import EventArray, TriggerEvents
from rigd.core.schema import SyncReport
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.take import EventSeries, Take, TakeWriter, open_take
from rigd.take.seal import finalize_take

W, H = 64, 48
N = 30_000
MAP = ClockMap(device_ref_us=400_000, rig_ref_us=5_000_000, rate=0.999905, frac_us=-0.4)
FIRST_PULSE = 5_040_000  # events before it get negative stored t (before t_offset)


@dataclass
class Written:
    path: Path
    t: np.ndarray
    """Rig times of ev0, as the reader gives them."""


def make_events(n: int, seed: int = 0) -> EventArray:
    """Runs of equal timestamps and a gap of empty milliseconds."""
    rng = np.random.default_rng(seed)
    dt = rng.choice(np.array([0, 0, 1, 3, 7], np.int64), n)
    dt[n // 2] = 25_000
    t = 400_000 + np.cumsum(dt)
    ev = EventArray.from_arrays(rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, 2, n), t)
    return ev[np.lexsort((ev.x, ev.p, ev.y, ev.t))]


def write(path: Path, storage: str = "columns", *, finalize: bool = True) -> Written:
    """ev0 with events and trigger edges, ev1 without events; pulses and a sync report."""
    cfg = WriterConfig(event_storage=storage, event_chunk=4096, fsync=False)  # type: ignore[arg-type]
    w = TakeWriter(path, rig_config_json="{}", take_id=path.stem, config=cfg, rigd_version="t")
    w.add_trigger(DeviceInfo(kind="trigger", spec="sim://t/trigger"))
    for name in ("ev0", "ev1"):
        w.add_event_sensor(name, DeviceInfo(kind="event_sensor", spec=f"sim://t/{name}"), W, H, "{}", "evt3")
    ev = make_events(N)
    if storage == "columns":
        for a, b in itertools.pairwise([0, 1, 5000, 17_001, N]):
            w.append_events("ev0", ev[a:b])
            w.flush()
    else:
        for i, p in enumerate(packets_of(ev, 3000, width=W, height=H)):
            w.append_packet("ev0", p)
            if i % 3 == 2:
                w.flush()
    trig_t = 400_100 + np.arange(12, dtype=np.int64) * 9_000
    w.append_triggers(
        "ev0", TriggerEvents(trig_t, np.tile([1, 0], 6).astype(np.uint8), np.zeros(12, np.uint8))
    )
    pulses = FIRST_PULSE + np.arange(4, dtype=np.int64) * 33_333
    w.append_pulses(PulseBatch(np.arange(4, dtype=np.int64), pulses, np.arange(4, dtype=np.int64)))
    if finalize:
        report = SyncReport(
            rate_hz=30.0, n_pulses=4, t_first_pulse_us=FIRST_PULSE, t_last_pulse_us=int(pulses[-1])
        )
        finalize_take(w, {"ev0": MAP, "ev1": MAP}, {}, report)
    w.close()
    return Written(path, MAP.to_rig(ev.t) if finalize else ev.t)


@pytest.fixture(scope="module", params=["columns", "evt_words"])
def written(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Written:
    return write(tmp_path_factory.mktemp("series") / f"{request.param}.h5", str(request.param))


def assert_same(got: EventArray, want: EventArray) -> None:
    for k in "xypt":
        np.testing.assert_array_equal(getattr(got, k), getattr(want, k), err_msg=k)
        assert getattr(got, k).dtype == getattr(want, k).dtype, k


def brute(take: Take, t0: int, t1: int) -> EventArray:
    ev = take.sensor("ev0").events()
    return ev[np.flatnonzero((ev.t >= t0) & (ev.t < t1))]


def test_one_series_per_sensor(written: Written) -> None:
    with open_take(written.path) as take:
        es = take.sensor("ev0")
        assert isinstance(es, EventSeries)
        assert take.sensor("ev0") is es  # the datasets stay open for the take's life
        assert es.name == "ev0"
        assert repr(es) == f"EventSeries({str(written.path)!r}, 'ev0')"
        assert es.geometry == (W, H)
        assert es.storage == written.path.stem
        assert es.evt_format == ("evt3" if es.storage == "evt_words" else None)
        assert es.count == len(es) == N
        assert es.span == (int(written.t[0]), int(written.t[-1]))
        assert es.t_offset == FIRST_PULSE
        assert es.trigger_count == len(es.triggers) == 12
        np.testing.assert_array_equal(es.triggers.t, MAP.to_rig(400_100 + np.arange(12) * 9_000))
        np.testing.assert_array_equal(es.events().t, written.t)


def test_unknown_sensor_names_what_exists(written: Written) -> None:
    with open_take(written.path) as take:
        with pytest.raises(TakeError, match=re.escape("no event sensor 'ev9' (has ['ev0', 'ev1'])")):
            take.sensor("ev9")
        with pytest.raises(TakeError, match=re.escape("no camera 'ev9' (has [])")):
            take.camera("ev9")  # the camera accessor says it the same way
    with pytest.raises(TakeError, match="the take is closed"):
        take.sensor("ev0")


def test_window_edges(written: Written) -> None:
    t = written.t
    with open_take(written.path) as take:
        es = take.sensor("ev0")
        for i in (0, 1, N // 2 - 1, N // 2, N // 2 + 1, N - 1):  # the gap is at N // 2
            ti = int(t[i])
            assert_same(es.events(ti, ti + 1), brute(take, ti, ti + 1))  # start inclusive
            assert_same(es.events(ti - 1, ti), brute(take, ti - 1, ti))  # end exclusive
            assert es.index(ti) == int(np.searchsorted(t, ti, side="left"))
            assert_same(es.events(t_start_us=ti), es.by_index(es.index(ti), N))
            assert_same(es.events(t_end_us=ti), es.by_index(0, es.index(ti)))
        ms = es.t_offset + 1000 * np.arange(-3, 4)  # ms-index edges, before t_offset too
        for a, b in itertools.product(ms, ms):
            assert_same(es.events(int(a), int(b)), brute(take, int(a), int(b)))
        assert_same(es.events(int(t[0]) - 10**9, int(t[-1]) + 10**9), es.events())
        assert es.index(int(t[-1]) + 1) == N
        assert es.index(int(t[0]) - 10**9) == 0


def test_empty_windows(written: Written) -> None:
    t = written.t
    gap = (int(t[N // 2 - 1]) + 1, int(t[N // 2]))  # no events inside
    with open_take(written.path) as take:
        es = take.sensor("ev0")
        for a, b in (gap, (int(t[-1]) + 1, int(t[-1]) + 50_000), (int(t[0]) - 50_000, int(t[0]))):
            assert len(es.events(a, b)) == 0
            assert es.events(a, b).t.dtype == np.int64
        assert len(es.events(int(t[100]), int(t[100]))) == 0  # zero length
        assert len(es.events(int(t[N - 10]), int(t[10]))) == 0  # reversed
        assert len(es.by_index(N, N + 10)) == 0
        assert len(es.by_index(50, 10)) == 0
        windows = list(es.iter(5_000))
        assert any(len(w) == 0 for w in windows)  # the gap's windows are there, empty
        assert_same(EventArray.concatenate(windows), es.events())
        start, counts = es.histogram(1000)
        assert counts.sum() == N
        assert counts[(gap[0] - start) // 1000 + 1 : (gap[1] - start) // 1000].sum() == 0
        empty = take.sensor("ev1")
        assert empty.count == len(empty) == 0
        assert empty.span is None
        assert len(empty.events()) == len(empty.events(int(t[0]), int(t[-1]))) == 0
        assert list(empty.iter(1000)) == []
        assert empty.histogram(1000)[1].size == 0
        assert empty.trigger_count == 0


def test_bad_arguments(written: Written) -> None:
    with open_take(written.path) as take:
        es = take.sensor("ev0")
        with pytest.raises(TakeError, match="multiple of 1000"):
            es.histogram(1500)
        with pytest.raises(TakeError, match="window_us must be positive"):
            next(iter(es.iter(0)))


def test_never_finalized_take(tmp_path: Path) -> None:
    wr = write(tmp_path / "columns.h5", finalize=False)
    with open_take(wr.path) as take:
        es = take.sensor("ev0")
        np.testing.assert_array_equal(es.events().t, wr.t)  # device time, all of it
        assert es.count == N
        assert es.span == (int(wr.t[0]), int(wr.t[-1]))
        assert_same(es.by_index(10, 20), es.events()[10:20])
        for read in (
            lambda: es.events(0, 10),
            lambda: es.index(0),
            lambda: es.histogram(),
            lambda: next(iter(es.iter(1000))),
        ):
            with pytest.raises(TakeError, match="rig time"):
                read()


class DsecSlicer:
    """DSEC's EventSlicer (uzh-rpg/DSEC scripts/utils/eventslicer.py), rewritten here on a take's
    sensor group: the window's ms bracket from `ms_to_idx` (start floored, end rounded up; None
    when the end's entry lies past the index), then the exact edges searched in its `t`. The
    index gets the entry past the last event's millisecond that the DSEC export writes."""

    def __init__(self, g: h5py.Group) -> None:
        self.g = g
        self.ms_to_idx = np.append(np.asarray(g["ms_to_idx"], np.int64), g["t"].shape[0])
        self.t_offset = int(g["t_offset"][()])

    def get_events(self, t_start_us: int, t_end_us: int) -> dict[str, np.ndarray] | None:
        assert t_start_us < t_end_us
        rel0, rel1 = t_start_us - self.t_offset, t_end_us - self.t_offset
        ms0, ms1 = rel0 // 1000, -(-rel1 // 1000)
        assert ms0 >= 0
        if ms0 >= self.ms_to_idx.size or ms1 >= self.ms_to_idx.size:
            return None
        i0, i1 = int(self.ms_to_idx[ms0]), int(self.ms_to_idx[ms1])
        t = np.asarray(self.g["t"][i0:i1], np.int64)
        a, b = int(np.searchsorted(t, rel0, side="left")), int(np.searchsorted(t, rel1, side="left"))
        out = {k: np.asarray(self.g[k][i0 + a : i0 + b]) for k in "pxy"}
        out["t"] = t[a:b] + self.t_offset
        return out


def test_window_is_dsec_event_slicer(tmp_path: Path, written: Written) -> None:
    """`events(t0, t1)` answers what the slicer reads from the columns take directly (its 1/0
    polarity as +1/-1), for either storage."""
    cols = write(tmp_path / "columns.h5") if written.path.stem != "columns" else written
    t = written.t
    rng = np.random.default_rng(4)
    with h5py.File(cols.path) as f, open_take(written.path) as take:
        ref = DsecSlicer(f["events/ev0"])
        es = take.sensor("ev0")
        off = es.t_offset
        assert off == ref.t_offset
        starts = [off, off + 1, off + 999, off + 1000, *rng.integers(off, int(t[-1]) + 2_000, 40).tolist()]
        lengths = [1, 999, 1000, 1001, 20_000, 100_000]
        for t0, length in itertools.product(starts, lengths):
            want = ref.get_events(int(t0), int(t0) + length)
            if want is None:  # past the slicer's index: the series still answers, up to the end
                continue
            ev = es.events(int(t0), int(t0) + length)
            for k in "xyt":
                np.testing.assert_array_equal(getattr(ev, k), want[k], err_msg=k)
            np.testing.assert_array_equal(ev.p, 2 * want["p"].astype(np.int8) - 1)
            assert ev.t.dtype == np.int64
