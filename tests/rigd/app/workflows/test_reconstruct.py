"""The reconstruction workflow called directly: one take through Dask on local threads."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from rigd.app.workflows.progress import ProgressUpdate
from rigd.app.workflows.reconstruct import ReconstructOptions, reconstruct_take, run_reconstruct
from tests.rigd.test_take_roundtrip import make_take


def test_reconstruct_writes_segments_and_snapshots_per_sensor(tmp_path: Path) -> None:
    path = make_take(tmp_path / "t.h5", n_events=60_000).path
    updates: list[ProgressUpdate] = []
    results = run_reconstruct(ReconstructOptions(takes=[path], out=tmp_path / "out"), updates.append)
    assert [r.take for r in results] == [str(path)]
    ev0 = results[0].sensors["ev0"]
    assert ev0.events_in == 60_000
    assert 0 < ev0.events_kept <= ev0.events_in
    dest = tmp_path / "out" / "take-1" / "ev0"
    segments = json.loads((dest / "segments.json").read_text())["segments"]
    assert len(segments) == ev0.segments > 0
    with np.load(dest / "snapshots.npz") as snaps:
        assert snaps["log_intensity"].shape[0] == ev0.segments
        assert snaps["times_us"].dtype == np.int64
    assert updates == [ProgressUpdate("reconstruct", str(path), 1, 1)]


def test_one_take_without_dask_gives_the_same_result(tmp_path: Path) -> None:
    path = make_take(tmp_path / "t.h5", n_events=60_000).path
    direct = reconstruct_take(path, tmp_path / "a")
    (batch,) = run_reconstruct(ReconstructOptions(takes=[path], out=tmp_path / "b"))
    assert direct == batch
    a = (tmp_path / "a" / "take-1" / "ev0" / "segments.json").read_text()
    assert a == (tmp_path / "b" / "take-1" / "ev0" / "segments.json").read_text()
