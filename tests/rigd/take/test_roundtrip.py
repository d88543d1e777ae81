"""Write a take in device time, finalize with known clock maps, read it back exactly."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware_sim.testing.takes import CAM_SHAPE, FIRST_PULSE, MAPS, H, W, Written, make_events, make_take
from rigd.core.devices import DeviceInfo
from rigd.core.errors import TakeError
from rigd.core.events import EventArray
from rigd.core.frames import Frame
from rigd.core.schema import SyncReport
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.take import TakeWriter, open_take, validate_take
from rigd.take.seal import fail_take, finalize_take


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> Written:
    return make_take(tmp_path_factory.mktemp("take") / "take.h5")


def test_finalized_take_is_valid(written: Written) -> None:
    assert validate_take(written.path) == []


def test_events_mapped_exactly(written: Written) -> None:
    want = MAPS["ev0"].to_rig(written.ev_t_device)
    with open_take(written.path) as take:
        assert take.status == "complete"
        assert take.take_id == "take-1"
        assert take.config == {"name": "test-rig"}
        ev = take.sensor("ev0").events()
        np.testing.assert_array_equal(ev.t, want)
        np.testing.assert_array_equal(ev.x, written.ev.x)
        np.testing.assert_array_equal(ev.y, written.ev.y)
        np.testing.assert_array_equal(ev.p, written.ev.p)
        assert ev.p.dtype == np.int8


def test_dsec_layout(written: Written) -> None:
    """A DSEC loader reads t relative to t_offset and indexes with ms_to_idx."""
    want = MAPS["ev0"].to_rig(written.ev_t_device)
    with h5py.File(written.path, "r") as f:
        g = f["events/ev0"]
        t_offset = int(g["t_offset"][()])
        assert t_offset == FIRST_PULSE
        t = g["t"][:]
        assert g["p"].dtype == np.uint8
        np.testing.assert_array_equal(g["p"][:], (written.ev.p > 0).astype(np.uint8))
        np.testing.assert_array_equal(t + t_offset, want)
        ms = g["ms_to_idx"][:]
        assert ms.dtype == np.uint64
        assert ms.size == t[-1] // 1000 + 1
        for i in range(ms.size):
            # DSEC definition, brute force: first index with t >= i ms.
            assert ms[i] == np.flatnonzero(t >= i * 1000)[0]
        np.testing.assert_array_equal(g["trigger/t_device"][:], written.trig_t_device)
        assert f.attrs["time_domain"] == "rig"


def test_frames_triggers_pulses(written: Written) -> None:
    with open_take(written.path) as take:
        fs = take.camera("cam0")
        assert len(fs) == 9
        want = MAPS["cam0"].to_rig(written.frame_t_device)
        np.testing.assert_array_equal(fs.timestamps_us, want)
        fr = fs[4]
        assert fr.t_exposure_start_us == want[4]
        assert fr.pulse_index == 104
        assert fr.frame_counter == 4
        assert (fr.image == 40).all()
        assert fs[-1].frame_counter == 8
        with pytest.raises(IndexError):
            fs[9]
        assert fs.index_at(int(want[3])) == 3
        assert fs.index_at(int(want[3]) - 1) == 2
        assert fs.index_at(int(want[0]) - 1) == -1
        assert fs.nearest(int(want[5]) + 10) == 5
        assert fs.nearest(int(want[5]) - 10) == 5
        assert fs.nearest(0) == 0
        tr = take.sensor("ev0").triggers
        np.testing.assert_array_equal(tr.t, MAPS["ev0"].to_rig(written.trig_t_device))
        pulses = take.pulses()
        np.testing.assert_array_equal(pulses.t_us, written.pulses_t)
        report = take.sync_report
        assert report is not None
        assert report.t_first_pulse_us == FIRST_PULSE


def _brute(t_rig: np.ndarray, a: int, b: int) -> np.ndarray:
    return np.flatnonzero((t_rig >= a) & (t_rig < b))


def test_window_edge_cases(written: Written) -> None:
    t_rig = MAPS["ev0"].to_rig(written.ev_t_device)
    first, last = int(t_rig[0]), int(t_rig[-1])
    mid = int(t_rig[len(t_rig) // 2])
    cases = [
        (first, last + 1),  # everything
        (first - 10_000, first),  # before the start: empty
        (last + 1, last + 50_000),  # past the end: empty
        (mid, mid + 1),  # a single timestamp (several events may share it)
        (mid, mid),  # empty window
        (FIRST_PULSE - 5000, FIRST_PULSE + 5000),  # events before t_offset (negative stored t)
        (first - 10**9, last + 10**9),
    ]
    with open_take(written.path) as take:
        for a, b in cases:
            idx = _brute(t_rig, a, b)
            ev = take.sensor("ev0").events(a, b)
            np.testing.assert_array_equal(ev.t, t_rig[idx], err_msg=f"window [{a}, {b})")
            np.testing.assert_array_equal(ev.x, written.ev.x[idx])
        assert len(take.sensor("ev0").events(mid, mid + 1)) >= 1
        np.testing.assert_array_equal(take.sensor("ev0").events(t_start_us=mid).t, t_rig[t_rig >= mid])
        np.testing.assert_array_equal(take.sensor("ev0").events(t_end_us=mid).t, t_rig[t_rig < mid])


@pytest.mark.slow
@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(a=st.integers(-200_000, 1_200_000), length=st.integers(0, 300_000))
def test_window_property(written: Written, a: int, length: int) -> None:
    t_rig = MAPS["ev0"].to_rig(written.ev_t_device)
    start = int(t_rig[0]) + a
    with open_take(written.path) as take:
        ev = take.sensor("ev0").events(start, start + length)
    np.testing.assert_array_equal(ev.t, t_rig[_brute(t_rig, start, start + length)])


def test_iter_events_covers_all_in_order(written: Written) -> None:
    t_rig = MAPS["ev0"].to_rig(written.ev_t_device)
    with open_take(written.path) as take:
        windows = list(take.sensor("ev0").iter(7_000))
    t0 = int(t_rig[0])
    assert len(windows) == -(-(int(t_rig[-1]) + 1 - t0) // 7_000)
    for k, w in enumerate(windows):
        assert ((w.t >= t0 + k * 7000) & (w.t < t0 + (k + 1) * 7000)).all()
    np.testing.assert_array_equal(np.concatenate([w.t for w in windows]), t_rig)


@pytest.mark.parametrize("codec", ["none", "zstd", "gzip"])
def test_other_codecs_roundtrip(tmp_path: Path, codec: str) -> None:
    wr = make_take(tmp_path / f"{codec}.h5", compression=codec, n_events=3000)
    assert validate_take(wr.path) == []
    with open_take(wr.path) as take:
        np.testing.assert_array_equal(take.sensor("ev0").events().t, MAPS["ev0"].to_rig(wr.ev_t_device))


@pytest.mark.parametrize("fsync", [False, True])
def test_fsync_makes_flushes_and_the_name_durable(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, fsync: bool
) -> None:
    """`writer.fsync`: every flush and the close reach the disk, then the directory entry."""
    synced: list[str] = []
    real_fsync = os.fsync

    def spy(fd: int) -> None:
        synced.append("dir" if stat.S_ISDIR(os.fstat(fd).st_mode) else "file")
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", spy)
    wr = make_take(tmp_path / "durable.h5", n_events=3000, fsync=fsync)
    # make_take flushes once by hand; close syncs the file, then its directory.
    assert synced == (["file", "file", "dir"] if fsync else [])
    assert validate_take(wr.path) == []


def test_unfinalized_take_opens_and_refuses_time_queries(tmp_path: Path) -> None:
    wr = make_take(tmp_path / "rec.h5", finalize=False)
    with open_take(wr.path) as take:
        assert take.status == "recording"
        assert take.sync_report is None
        np.testing.assert_array_equal(take.sensor("ev0").events().t, wr.ev_t_device)  # device time, all of it
        assert len(take.camera("cam0")) == 9
        with pytest.raises(TakeError, match="never finalized"):
            take.sensor("ev0").events(0, 10)
        with pytest.raises(TakeError, match="never finalized"):
            take.camera("cam0").index_at(0)
        with pytest.raises(TakeError, match="never finalized"):
            next(iter(take.sensor("ev0").iter(1000)))


def _writer(path: Path) -> TakeWriter:
    w = TakeWriter(
        path, rig_config_json="{}", take_id="x", config=WriterConfig(event_chunk=1024), rigd_version="t"
    )
    w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="s"), W, H, "{}")
    return w


def test_writer_rejects_decreasing_t_without_writing(tmp_path: Path) -> None:
    w = _writer(tmp_path / "a.h5")
    good = make_events(100, 1000)
    w.append_events("ev0", good)
    older = make_events(10, 500)
    with pytest.raises(TakeError, match=r"ev0.*event 0 of the batch"):
        w.append_events("ev0", older)
    t = np.array([5_000_000, 5_000_010, 5_000_005], np.int64)
    unsorted = EventArray.from_arrays([1, 2, 3], [1, 2, 3], [1, 1, 1], t)
    with pytest.raises(TakeError, match=r"ev0.*event 2 of the batch"):
        w.append_events("ev0", unsorted)
    w.close()
    with open_take(tmp_path / "a.h5") as take:
        np.testing.assert_array_equal(take.sensor("ev0").events().t, good.t)


def test_writer_rejects_out_of_geometry_without_writing(tmp_path: Path) -> None:
    w = _writer(tmp_path / "b.h5")
    bad = EventArray.from_arrays([1, W, 2], [0, 0, 0], [1, 0, 1], [10, 11, 12])
    with pytest.raises(TakeError, match=rf"ev0.*event 1 of the batch has x={W}"):
        w.append_events("ev0", bad)
    bad_y = EventArray.from_arrays([1], [H], [1], [10])
    with pytest.raises(TakeError, match=rf"y={H}"):
        w.append_events("ev0", bad_y)
    ok = EventArray.from_arrays([W - 1], [H - 1], [1], [10])
    w.append_events("ev0", ok)  # the refused batches did not move last_t either
    w.close()
    with open_take(tmp_path / "b.h5") as take:
        ev = take.sensor("ev0").events()
        assert len(ev) == 1
        assert int(ev.x[0]) == W - 1


def test_writer_rejects_wrong_frame_shape_and_writes_after_close(tmp_path: Path) -> None:
    w = TakeWriter(
        tmp_path / "c.h5", rig_config_json="{}", take_id="x", config=WriterConfig(), rigd_version="t"
    )
    w.add_camera("cam0", DeviceInfo(kind="rgb_camera", spec="s"), CAM_SHAPE, np.uint8, "{}")
    with pytest.raises(TakeError, match="frames/cam0/images"):
        w.append_frame("cam0", Frame(np.zeros((2, 2), np.uint8), 0, 1, 0, 0))
    with pytest.raises(TakeError, match="added twice"):
        w.add_camera("cam0", DeviceInfo(kind="rgb_camera", spec="s"), CAM_SHAPE, np.uint8, "{}")
    w.close()
    w.close()  # idempotent
    with pytest.raises(TakeError, match="closed"):
        w.append_frame("cam0", Frame(np.zeros(CAM_SHAPE, np.uint8), 0, 1, 0, 0))


def test_fail_marks_take_failed_and_keeps_data(tmp_path: Path) -> None:
    w = _writer(tmp_path / "f.h5")
    ev = make_events(500, 1000)
    w.append_events("ev0", ev)
    fail_take(w, "disk on fire")
    w.close()
    with open_take(tmp_path / "f.h5") as take:
        assert take.status == "failed"
        assert len(take.sensor("ev0").events()) == 500
        assert take.summary().failure_reason == "disk on fire"


def test_finalize_needs_every_clock_map(tmp_path: Path) -> None:
    w = _writer(tmp_path / "m.h5")
    w.append_events("ev0", make_events(10, 1000))
    report = SyncReport(rate_hz=30.0, n_pulses=0, t_first_pulse_us=None, t_last_pulse_us=None)
    with pytest.raises(TakeError, match="no clock map for device 'ev0'"):
        finalize_take(w, {}, {}, report)
    finalize_take(w, {"ev0": ClockMap(0, 7, 1.0)}, {}, report)  # nothing was changed by the refusal
    w.close()
    with open_take(tmp_path / "m.h5") as take:
        # No pulse in the report: t_offset is the first event.
        ev = take.sensor("ev0").events()
        np.testing.assert_array_equal(ev.t, make_events(10, 1000).t + 7)
        assert validate_take(tmp_path / "m.h5") == []


def test_stats_count_items_and_bytes(tmp_path: Path) -> None:
    w = _writer(tmp_path / "s.h5")
    w.append_events("ev0", make_events(5000, 0))
    w.flush()
    st_ = w.stats["ev0"]
    assert st_.items == 5000
    assert st_.raw_bytes == 5000 * 13
    assert st_.stored_bytes > 0
    w.close()
