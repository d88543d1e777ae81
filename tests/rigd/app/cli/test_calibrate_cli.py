"""`rigd calibrate` as a user meets it: each stage in its own unit (frames searched for the board,
images searched), so a run of minutes does not look hung; each warning said once."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import pytest
from typer.testing import CliRunner

from firmware_sim.testing.board import BOARD
from firmware_sim.testing.stereo import BOARD as STEREO_BOARD
from firmware_sim.testing.stereo import stereo_board_take
from rigd.app.cli import app
from rigd.app.testing.board import capture_board_take

runner = CliRunner()


@pytest.fixture(scope="module")
def board_take(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cap = capture_board_take(
        tmp_path_factory.mktemp("e2calib"), 1.5, (480, 270), world="t-cli-e2calib", clock="virtual"
    )
    return cap.path


def _stages(stderr: str, title: str) -> list[str]:
    return [line.removeprefix(f"{title}: ") for line in stderr.splitlines() if line.startswith(f"{title}: ")]


@pytest.mark.slow
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
    r = runner.invoke(app, ["-v", *args])
    assert r.exit_code == 0, r.output
    stages = _stages(r.stderr, "calibrate events")
    names = [re.split(r"[ :]", s)[0] for s in stages]
    assert names == ["read", "check", "reconstruct", "detect", "calibrate", "write"], stages
    detect = stages[3]
    assert "frames searched for the board" in detect
    assert detect.endswith("ev0, integrate")
    assert "reconstructing" in stages[2]


@pytest.mark.slow
def test_calibrate_rig_from_a_take_counts_frames_per_camera(tmp_path: Path) -> None:
    take = stereo_board_take(tmp_path / "stereo.h5", n_views=6)
    r = runner.invoke(
        app, ["-v", "calibrate", "rig", str(take), "-b", STEREO_BOARD, "-o", str(tmp_path / "rig.yaml")]
    )
    assert r.exit_code == 0, r.output
    stages = _stages(r.stderr, "calibrate rig")
    assert "detect (6 frames searched for the board): cam0" in stages
    assert "detect (6 frames searched for the board): cam1" in stages
    assert any(s.startswith("calibrate") for s in stages)


@pytest.mark.slow
def test_calibration_warnings_are_said_once(board_take: Path, tmp_path: Path) -> None:
    out = tmp_path / "ev0.yaml"
    r = runner.invoke(app, ["calibrate", "events", str(board_take), "-s", "ev0", "-b", BOARD, "-o", str(out)])
    assert r.exit_code == 0, r.output
    lines = r.stderr.splitlines()
    said = [line.removeprefix("warning: ev0: ") for line in lines if line.startswith("warning:")]
    assert said, r.stderr  # this take's board covers little of the image: there is something to say
    for text in said:
        assert r.stderr.count(text) == 1, (text, r.stderr)


@pytest.mark.slow
def test_rig_output_says_what_each_number_is(tmp_path: Path) -> None:
    take = stereo_board_take(tmp_path / "stereo.h5", n_views=8)
    out, report = tmp_path / "rig.yaml", tmp_path / "rig.html"
    r = runner.invoke(
        app, ["calibrate", "rig", str(take), "-b", STEREO_BOARD, "-o", str(out), "--report", str(report)]
    )
    assert r.exit_code == 0, r.output
    text = " ".join(r.stderr.split())
    assert "t=[" not in text
    assert "cam0: the reference (origin of the rig frame)" in text
    centre = re.search(r"cam1: centre at \(([-+0-9., ]+)\) m ±[0-9.]+ m in cam0's frame", text)
    assert centre is not None, text
    x = float(centre.group(1).split(",")[0])
    assert 0.09 < x < 0.11  # cam1 sits 10 cm to the right of cam0
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    yaml_rms = fs.getNode("cam1_avg_reprojection_error").real()
    fs.release()
    line = next(line for line in r.stderr.splitlines() if line.startswith("cam1: centre"))
    own = re.search(
        r"RMS ([0-9.]+) px own fit \(\d+ views, avg_reprojection_error\), ([0-9.]+) px rig fit", line
    )
    assert own is not None, line
    assert float(own.group(1)) == pytest.approx(yaml_rms, abs=6e-4)
    html = report.read_text()
    assert "rig RMS px (views)" in html
    assert "own RMS px (views)" in html
    assert "avg_reprojection_error" in html


@pytest.mark.slow
def test_intrinsics_report_says_why_a_model_was_chosen(tmp_path: Path) -> None:
    take = stereo_board_take(tmp_path / "stereo.h5", n_views=10)
    report = tmp_path / "rig.html"
    r = runner.invoke(
        app,
        [
            "calibrate",
            "rig",
            str(take),
            "-b",
            STEREO_BOARD,
            "-o",
            str(tmp_path / "rig.yaml"),
            "--report",
            str(report),
        ],
    )
    assert r.exit_code == 0, r.output
    html = report.read_text()
    assert "at least 2 % lower" in html
    rows = re.findall(
        r"<tr><td>(\w+)</td><td>\d+</td><td>([0-9.]*)</td><td>([0-9.]*)</td><td>([^<]*)</td></tr>", html
    )
    assert rows
    for model, _train, held_out, outcome in rows:
        assert outcome, f"{model}: no outcome"
        if held_out and outcome != "chosen":
            assert "lower than" in outcome or "no lower than" in outcome or "beaten" in outcome, outcome
    assert "RMS, all corners" not in html  # drawn into the figure, not the page text
    assert "dashed: the RMS over every corner" in html


def test_report_ticks_are_round_numbers() -> None:
    from calibration.report import nice_step

    assert nice_step(0.1386) == pytest.approx(0.05)
    assert nice_step(0.9) == pytest.approx(0.2)
    assert nice_step(3.0) == pytest.approx(0.5)


@pytest.mark.slow
def test_calibrate_rig_on_a_take_with_ground_truth_prints_its_error(tmp_path: Path) -> None:
    """A take that carries its ground truth (as a sim take does from its capture): the rig
    calibration is scored against it, and storing the result into the take keeps the truth."""
    import json

    import h5py
    import numpy as np

    from firmware_sim.testing.stereo import DIST, SIZE, T1
    from firmware_sim.testing.stereo import K as K_TRUE
    from rigd.take.calibration import GROUND_TRUTH_SOURCE, read_ground_truth, store_calibration

    take = stereo_board_take(tmp_path / "stereo.h5", n_views=6)
    intr = {"K": K_TRUE.tolist(), "dist": DIST.tolist(), "image_size": list(SIZE)}
    for name, t in (("cam0", np.zeros(3)), ("cam1", T1)):
        pose = {"R": np.eye(3).tolist(), "t": t.tolist()}
        store_calibration(take, name, intr, pose, source=GROUND_TRUTH_SOURCE)
    args = ["calibrate", "rig", str(take), "-b", STEREO_BOARD, "--model", "k1k2"]
    r = runner.invoke(app, [*args, "-o", str(tmp_path / "rig.json"), "--into-take", str(take)])
    assert r.exit_code == 0, r.output
    lines = [ln for ln in r.stderr.splitlines() if "vs simulator ground truth" in ln]
    print("\n".join(lines))
    assert [ln.split()[0] for ln in lines] == ["cam0", "cam1"], r.stderr
    for ln in lines:
        focal = re.search(r"focal ([0-9.]+) px", ln)
        centre = re.search(r"centre ([0-9.]+) mm", ln)
        assert focal is not None, ln
        assert centre is not None, ln
        assert float(focal[1]) < 3.0, ln  # 6 noisy views of a 320x240 camera with f = 300 px
        assert float(centre[1]) < 10.0, ln
    with h5py.File(take, "r") as f:
        truth = read_ground_truth(f)
        stored = json.loads(f["calibration/cam1/result_json"][()])
    assert set(truth) == {"cam0", "cam1"}
    assert stored["source"] != GROUND_TRUTH_SOURCE
    np.testing.assert_allclose(stored["ground_truth"]["pose"]["t"], T1)
