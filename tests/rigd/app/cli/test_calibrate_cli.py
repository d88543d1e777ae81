"""`rigd calibrate` as a user meets it: each stage in its own unit (frames searched for the board,
images searched), so a run of minutes does not look hung; each warning said once."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from bench.e2calib import BOARD, capture_board_take
from rigd.app.cli import app
from tests.rigd.app.workflows.takes import BOARD as STEREO_BOARD
from tests.rigd.app.workflows.takes import stereo_board_take

runner = CliRunner()


@pytest.fixture(scope="module")
def board_take(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cap = capture_board_take(
        tmp_path_factory.mktemp("e2calib"), 1.5, (480, 270), world="t-cli-e2calib", clock="virtual"
    )
    return cap.path


def _stages(stderr: str, title: str) -> list[str]:
    return [line.removeprefix(f"{title}: ") for line in stderr.splitlines() if line.startswith(f"{title}: ")]


def test_calibrate_events_reports_frames_per_stage(board_take: Path, tmp_path: Path) -> None:
    out = tmp_path / "ev0.yaml"
    args = [
        "calibrate",
        "events",
        str(board_take),
        "-s",
        "ev0",
        "-b",
        BOARD,
        "-m",
        "integrate",
        "-o",
        str(out),
    ]
    r = runner.invoke(app, args)
    assert r.exit_code == 0, r.output
    stages = _stages(r.stderr, "calibrate events")
    names = [re.split(r"[ :]", s)[0] for s in stages]
    assert names == ["read", "check", "reconstruct", "detect", "calibrate", "write"], stages
    detect = stages[3]
    assert "frames searched for the board" in detect
    assert detect.endswith("ev0, integrate")
    assert "reconstructing" in stages[2]


def test_calibrate_rig_from_a_take_counts_frames_per_camera(tmp_path: Path) -> None:
    take = stereo_board_take(tmp_path / "stereo.h5", n_views=6)
    r = runner.invoke(
        app, ["calibrate", "rig", str(take), "-b", STEREO_BOARD, "-o", str(tmp_path / "rig.yaml")]
    )
    assert r.exit_code == 0, r.output
    stages = _stages(r.stderr, "calibrate rig")
    assert "detect (6 frames searched for the board): cam0" in stages
    assert "detect (6 frames searched for the board): cam1" in stages
    assert any(s.startswith("calibrate") for s in stages)


def test_calibration_warnings_are_said_once(board_take: Path, tmp_path: Path) -> None:
    out = tmp_path / "ev0.yaml"
    r = runner.invoke(app, ["calibrate", "events", str(board_take), "-s", "ev0", "-b", BOARD, "-o", str(out)])
    assert r.exit_code == 0, r.output
    lines = r.stderr.splitlines()
    said = [line.removeprefix("warning: ev0: ") for line in lines if line.startswith("warning:")]
    assert said, r.stderr  # this take's board covers little of the image: there is something to say
    for text in said:
        assert r.stderr.count(text) == 1, (text, r.stderr)
