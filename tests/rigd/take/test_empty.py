"""Devices that recorded nothing (capped lens, unplugged from the start, no trigger cable) and
takes without pulses: finalize and recovery complete them with empty, valid datasets."""

from __future__ import annotations

import itertools
from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from rigd.app.cli import app
from rigd.app.testing.crash import OFF_CAM, OFF_EV, PERIOD, RIG0, open_writer, step
from rigd.core.schema import SyncReport
from rigd.core.timebase import ClockMap
from rigd.take import Take, TakeWriter, find_unfinished, recover_take, validate_take
from rigd.take.seal import finalize_take

pytestmark = pytest.mark.slow

N = 20
MAPS = {"cam0": ClockMap(OFF_CAM, 0, 1.0, 0.0), "ev0": ClockMap(OFF_EV, 0, 1.0, 0.0)}
#: (frames, events, trigger edges, pulses): every combination with something empty.
COMBOS = [c for c in itertools.product((0, 1), repeat=4) if not all(c)]


def _write(path: Path, frames: int, events: int, edges: int, pulses: int) -> TakeWriter:
    w = open_writer(path)
    for k in range(N):
        s = step(k)
        if pulses:
            w.append_pulses(s.pulse)
        if frames:
            w.append_frame("cam0", s.frame)
        if events:
            w.append_events("ev0", s.events)
        if edges:
            w.append_triggers("ev0", s.triggers, s.packet_host_ns)
    w.flush()
    return w


def _check_readable(path: Path, frames: int, events: int) -> None:
    assert validate_take(path) == []
    with h5py.File(path, "r") as f:
        complete = f.attrs["status"] == "complete"
    for args in ((), ("--json",)):
        res = CliRunner().invoke(app, ["inspect", str(path), *args])
        assert res.exit_code == (0 if complete else 1), res.output
    res = CliRunner().invoke(app, ["inspect", str(path), "--json"])
    assert res.exit_code in (0, 1), res.output
    with Take(path) as take:
        assert len(take.sensor("ev0").events().t) == (N * 300 if events else 0)
        fs = take.camera("cam0")
        assert len(fs) == (N if frames else 0)
        assert len(fs.timestamps_us) == len(fs)
        take.summary()
    with h5py.File(path, "r") as f:
        g = f["events/ev0"]
        assert g["t"].dtype == np.int64
        assert g["x"].shape == g["t"].shape
        if f.attrs["status"] == "complete":
            assert g["ms_to_idx"].shape[0] == (0 if not events else g["ms_to_idx"].shape[0])
            assert g["ms_to_idx"].dtype == np.uint64
        assert f["frames/cam0/images"].shape[1:] == (6, 8)


@pytest.mark.parametrize(("frames", "events", "edges", "pulses"), COMBOS)
def test_finalize_with_empty_devices(
    tmp_path: Path, frames: int, events: int, edges: int, pulses: int
) -> None:
    path = tmp_path / "e.h5"
    w = _write(path, frames, events, edges, pulses)
    first = RIG0 if pulses else None
    last = RIG0 + (N - 1) * PERIOD if pulses else None
    report = SyncReport(
        rate_hz=1e6 / PERIOD, n_pulses=N if pulses else 0, t_first_pulse_us=first, t_last_pulse_us=last
    )
    finalize_take(w, MAPS, {"cam0": np.arange(N if frames else 0, dtype=np.int64)}, report)
    w.close()
    _check_readable(path, frames, events)
    with Take(path) as take:
        assert take.status == "complete"
        ev = take.sensor("ev0").events()
        if events:
            np.testing.assert_array_equal(ev.t[:300], step(0).events.t - OFF_EV)
        rep = take.sync_report
        assert rep is not None
        if not frames:
            assert "cam0: recorded nothing (0 frames)" in rep.warnings
        if not events:
            assert any(w.startswith("ev0: recorded no") for w in rep.warnings)
        elif not edges:
            assert any("ev0: recorded no trigger edges" in w for w in rep.warnings)
    with h5py.File(path, "r") as f:
        g = f["events/ev0"]
        t_offset = int(g["t_offset"][()])
        source = g.attrs["t_offset_source"]
        if pulses:
            assert (t_offset, source) == (RIG0, "first_pulse")
        elif events:
            assert (t_offset, source) == (int(step(0).events.t[0]) - OFF_EV, "first_event")
        else:
            assert (t_offset, source) == (0, "none")
        if not events:
            assert g["ms_to_idx"].shape == (0,)


@pytest.mark.parametrize(("frames", "events", "edges", "pulses"), COMBOS)
def test_killed_take_with_empty_devices_recovers(
    tmp_path: Path, frames: int, events: int, edges: int, pulses: int
) -> None:
    path = tmp_path / "k.h5"
    _write(path, frames, events, edges, pulses).close()  # status stays "recording": a kill
    assert find_unfinished(tmp_path) == [path]
    rr = recover_take(path)
    assert rr.sealed
    holding = frames or events
    # Sealed complete unless no pulse ties anything, or the only data has no clock to fit.
    tied = (frames or edges) if holding else True
    if pulses and tied:
        assert rr.outcome == "sealed", rr
    else:
        assert rr.outcome == "sealed_failed", rr
    _check_readable(path, frames, events)
    assert find_unfinished(tmp_path) == []
    with Take(path) as take:
        if rr.outcome == "sealed":
            rep = take.sync_report
            assert rep is not None
            if not frames:
                assert "cam0: recorded nothing (0 frames)" in rep.warnings
            if not events and not edges:
                assert "ev0: recorded nothing (0 events, 0 trigger edges)" in rep.warnings
