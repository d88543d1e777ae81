# ruff: noqa: N806  (K, R, T follow the notation of the calibration literature)
"""Outputs (OpenCV YAML, Kalibr camchain, JSON, HTML report) and the `calibrate` CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import typer
import yaml
from typer.testing import CliRunner

from calibration.boards import parse_board
from calibration.errors import CalibrationError
from calibration.intrinsics import calibrate_intrinsics
from calibration.io import kalibr_camchain, read_opencv_yaml, write_json, write_opencv_yaml
from calibration.report import write_report
from rigd.app.commands.calibrate import calibrate_app
from tests.calibration.real_data import DATA, REAL_BOARD, real_files

app = typer.Typer()
app.add_typer(calibrate_app, name="calibrate")
runner = CliRunner()


@pytest.mark.slow
def test_yaml_json_kalibr_and_report(real_detections, tmp_path: Path) -> None:
    board = parse_board(REAL_BOARD)
    res = calibrate_intrinsics(real_detections["left"][0], board, camera="left")
    write_opencv_yaml(res, tmp_path / "cam.yaml")
    K, dist, size = read_opencv_yaml(tmp_path / "cam.yaml")
    assert np.allclose(K, res.camera_matrix())
    assert np.allclose(dist, res.dist_coeffs())
    assert size == (640, 512)
    write_json(res, tmp_path / "cam.json")
    data = json.loads((tmp_path / "cam.json").read_text())
    assert data["model"] == res.model
    assert len(data["views"][0]["residuals"]) == 54
    chain = kalibr_camchain({"left": res})
    assert chain["cam0"]["distortion_model"] == "radtan"  # type: ignore[index]
    assert chain["cam0"]["cam_overlaps"] == []  # type: ignore[index]
    rich = calibrate_intrinsics(real_detections["left"][0], board, camera="left", model="rational")
    with pytest.raises(CalibrationError, match="radtan"):
        kalibr_camchain({"left": rich})
    write_report(tmp_path / "r.html", [res], samples={"left": np.zeros((512, 640), np.uint8) + 100})
    html = (tmp_path / "r.html").read_text()
    assert html.count("data:image/png;base64,") == 5
    assert "reprojection RMS per view" in html


@pytest.mark.slow
def test_cli_intrinsics_json_yaml_report(tmp_path: Path) -> None:
    files = [str(f) for f in real_files("left")]
    out = tmp_path / "left.yaml"
    r = runner.invoke(
        app,
        [
            "calibrate",
            "intrinsics",
            "--board",
            REAL_BOARD,
            *files,
            "--out",
            str(out),
            "--json",
            "--report",
            str(tmp_path / "left.html"),
            "--camera",
            "left",
        ],
    )
    assert r.exit_code == 0, r.output
    data = json.loads(r.stdout)
    assert data["camera"] == "left"
    assert 510 < data["K"][0][0] < 530
    assert "fx" in data["std_devs"]
    assert len(data["per_view_rms_px"]) == 16
    assert out.exists()
    assert (tmp_path / "left.html").exists()


@pytest.mark.slow
def test_cli_rig_from_image_sets(tmp_path: Path) -> None:
    real_files("left")
    out = tmp_path / "rig.json"
    r = runner.invoke(
        app,
        [
            "calibrate",
            "rig",
            "--board",
            REAL_BOARD,
            "--camera",
            f"left={DATA}/left*.jpg",
            "--camera",
            f"right={DATA}/right*.jpg",
            "--out",
            str(out),
            "--json",
            "--kalibr",
            str(tmp_path / "camchain.yaml"),
        ],
    )
    assert r.exit_code == 0, r.output
    data = json.loads(r.stdout)
    assert data["n_views"] == 16
    assert 0.05 < abs(data["cameras"][1]["t"][0]) < 0.2
    chain = yaml.safe_load((tmp_path / "camchain.yaml").read_text())
    assert np.asarray(chain["cam1"]["T_cn_cnm1"]).shape == (4, 4)
    # Kalibr's own layout: kalibr_camera_validator's getCamOverlaps reads cam_overlaps
    assert chain["cam0"]["cam_overlaps"] == [1]
    assert chain["cam1"]["cam_overlaps"] == [0]


def test_cli_errors_exit_2(tmp_path: Path) -> None:
    blank = tmp_path / "blank.png"
    import cv2

    cv2.imwrite(str(blank), np.full((100, 100), 128, np.uint8))
    r = runner.invoke(
        app, ["calibrate", "intrinsics", "--board", REAL_BOARD, str(blank), "--out", str(tmp_path / "x.yaml")]
    )
    assert r.exit_code == 2
    assert "not found" in r.output
    r = runner.invoke(
        app,
        [
            "calibrate",
            "intrinsics",
            "--board",
            "chessboard:9x6",
            str(blank),
            "--out",
            str(tmp_path / "x.yaml"),
        ],
    )
    assert r.exit_code == 2
    assert "bad board spec" in r.output
