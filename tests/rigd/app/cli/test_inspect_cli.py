"""`rigd inspect` as a person reads it: no `None` cells, losses as a table and warnings as
sentences, no empty tables, the clock the times are in, thumbnails that sample where the data is."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

import rigd.products.inspect as inspect_mod
from firmware_sim.testing.takes import make_take
from rigd.app.cli import app
from rigd.core.events import EventArray
from rigd.core.schema import LossRecord, SyncReport
from rigd.evt import RawHeader, write_raw

runner = CliRunner()


@pytest.fixture(scope="module")
def lossy_take(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finalized take without sync fits (so per-device sync cells are missing), with losses and
    warnings in its report."""
    path = make_take(tmp_path_factory.mktemp("i") / "take.h5").path
    with h5py.File(path, "r+") as f:
        node = f["sync/report_json"]
        report = SyncReport.model_validate_json(node[()])
        report.losses = [
            LossRecord(device="cam0", what="frames", count=2, reason="transport dropped frames 4 and 20"),
            LossRecord(device="ev0", what="events", count=1500, reason="writer queue full for 0.2 s"),
        ]
        report.warnings = ["ev0: event rate near the limit of its link"]
        del f["sync/report_json"]
        f["sync/report_json"] = report.model_dump_json()
    return path


@pytest.fixture(scope="module")
def converted_take(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An event-only take converted from a RAW recording: its times are the sensor's own clock."""
    d = tmp_path_factory.mktemp("c")
    rng = np.random.default_rng(3)
    n = 20_000
    t = 1_000_000 + np.cumsum(rng.integers(1, 50, n))
    events = EventArray.from_arrays(rng.integers(0, 64, n), rng.integers(0, 48, n), rng.integers(0, 2, n), t)
    write_raw(d / "rec.raw", RawHeader(width=64, height=48), events)
    r = runner.invoke(app, ["convert", str(d / "rec.raw"), str(d / "rec.h5")])
    assert r.exit_code == 0, r.output
    return d / "rec.h5"


def test_missing_values_are_a_dash_and_losses_a_table(lossy_take: Path) -> None:
    r = runner.invoke(app, ["inspect", str(lossy_take)])
    assert r.exit_code == 0, r.output
    text = r.stdout
    assert "None" not in text
    assert "—" in text  # sync columns without a fit
    for repr_mark in ("{", "[", "'", "LossRecord"):  # no Python reprs
        assert repr_mark not in text
    assert "losses" in text
    assert "transport dropped frames 4 and 20" in text
    assert "1,500" in text
    assert "warning: ev0: event rate near the limit of its link" in text
    assert "trigger pulses: 10" in text


def test_an_event_only_take_has_no_camera_table(converted_take: Path) -> None:
    r = runner.invoke(app, ["inspect", str(converted_take)])
    assert r.exit_code == 0, r.output
    assert "camera" not in r.stdout
    assert "sensor" in r.stdout
    assert "the recording's own clock (no trigger box)" in r.stdout
    assert "rig time" not in r.stdout
    assert "None" not in r.stdout


def _labels(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    seen: list[str] = []
    tile = inspect_mod._tile

    def record(img: np.ndarray, width: int, height: int, label: str, events: bool = False) -> np.ndarray:
        seen.append(label)
        return tile(img, width, height, label, events)

    monkeypatch.setattr(inspect_mod, "_tile", record)
    return seen


def test_thumbnails_of_a_converted_take_are_not_labelled_rig_time(
    converted_take: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    labels = _labels(monkeypatch)
    r = runner.invoke(app, ["inspect", str(converted_take), "--thumbnails", str(tmp_path / "s.png")])
    assert r.exit_code == 0, r.output
    assert len(labels) == 4
    assert all(label.endswith("(own clock)") for label in labels), labels


def test_thumbnail_columns_do_not_repeat_a_frame(
    lossy_take: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The events of this take end before its frames start: columns sample the frames.
    labels = _labels(monkeypatch)
    r = runner.invoke(app, ["inspect", str(lossy_take), "--thumbnails", str(tmp_path / "s.png")])
    assert r.exit_code == 0, r.output
    frames = [label.split(" ")[1] for label in labels if label.startswith("cam0")]
    assert len(frames) == 4
    assert len(set(frames)) == 4, frames
    assert all(label.endswith("(rig)") for label in labels)
