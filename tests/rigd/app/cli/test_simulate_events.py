"""`rigd simulate-events` says what it read (which camera of a take) and warns, once, when the
sub-step cap cut the time resolution it was asked for."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from firmware_sim.testing.frames import make_folder
from firmware_sim.testing.stereo import stereo_board_take
from rigd.app.cli import app

runner = CliRunner()


@pytest.mark.slow
def test_from_a_take_it_names_the_camera(tmp_path: Path) -> None:
    take = stereo_board_take(tmp_path / "stereo.h5", n_views=3)
    r = runner.invoke(app, ["simulate-events", str(take), "--out", str(tmp_path / "a.h5"), "--substeps", "1"])
    assert r.exit_code == 0, r.output
    assert "camera cam0 (the first of cam0, cam1; --camera picks another)" in " ".join(r.stderr.split())
    r = runner.invoke(
        app,
        [
            "simulate-events",
            str(take),
            "--out",
            str(tmp_path / "b.h5"),
            "--substeps",
            "1",
            "--camera",
            "cam1",
        ],
    )
    assert r.exit_code == 0, r.output
    text = " ".join(r.stderr.split())
    assert "camera cam1" in text
    assert "first of" not in text


def test_hitting_the_sub_step_cap_is_one_warning_with_the_count(tmp_path: Path) -> None:
    folder = make_folder(tmp_path)  # 3 px of motion per frame
    args = ["simulate-events", str(folder), "--out", str(tmp_path / "ev.h5"), "--fps", "30"]
    r = runner.invoke(app, [*args, "--max-px-per-step", "0.5", "--max-substeps", "2"])
    assert r.exit_code == 0, r.output
    text = " ".join(r.stderr.split())
    assert text.count("warning:") == 1, text
    found = re.search(r"warning: (\d+) of 4 frame steps hit the sub-step cap \(--max-substeps 2;", text)
    assert found is not None, text
    assert int(found.group(1)) >= 1
    assert "Raise --max-substeps to" in text


@pytest.mark.slow
def test_no_warning_when_the_cap_is_not_reached(tmp_path: Path) -> None:
    folder = make_folder(tmp_path)
    r = runner.invoke(app, ["simulate-events", str(folder), "--out", str(tmp_path / "ev.h5"), "--fps", "30"])
    assert r.exit_code == 0, r.output
    assert "warning:" not in r.stderr
