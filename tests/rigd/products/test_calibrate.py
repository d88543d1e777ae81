# ruff: noqa: N806  (R follows the notation of the calibration literature)
"""The calibration workflows called directly, as the daemon or a web page would: typed options in,
typed results out, progress through the callback, RigdErrors on failure."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibration.boards import parse_board
from calibration.errors import BoardSpecError, CalibrationError, NoBoardFoundError
from firmware_sim.testing.stereo import BOARD, T1, stereo_board_take
from firmware_sim.testing.takes import make_take
from rigd.core.errors import RigdError
from rigd.core.progress import ProgressUpdate
from rigd.products.calibrate import (
    EventsOptions,
    ImageSets,
    IntrinsicsOptions,
    RigOptions,
    TakeSource,
    event_times,
    glob_images,
    run_events,
    run_intrinsics,
    run_rig,
)
from rigd.take.reader import open_take
from tests.calibration.real_data import DATA, REAL_BOARD, real_files


@pytest.fixture(scope="module")
def stereo_take(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return stereo_board_take(tmp_path_factory.mktemp("stereo") / "stereo.h5")


def test_board_option_takes_a_spec_string_or_a_board_spec(tmp_path: Path) -> None:
    spec = parse_board(REAL_BOARD)
    assert IntrinsicsOptions(images=[], board=REAL_BOARD, out=tmp_path / "x.yaml").board == spec
    assert IntrinsicsOptions(images=[], board=spec, out=tmp_path / "x.yaml").board == spec
    with pytest.raises(BoardSpecError, match="bad board spec"):
        IntrinsicsOptions(images=[], board="chessboard:9x6", out=tmp_path / "x.yaml")


@pytest.mark.slow
def test_intrinsics_writes_result_report_and_take_entry(stereo_take: Path, tmp_path: Path) -> None:
    updates: list[ProgressUpdate] = []
    options = IntrinsicsOptions(
        images=real_files("left"),
        board=REAL_BOARD,
        out=tmp_path / "cam0.json",
        camera="cam0",
        report=tmp_path / "cam0.html",
        into_take=stereo_take,
    )
    result = run_intrinsics(options, updates.append)
    assert result.camera == "cam0"
    assert len(result.views) == 16
    assert 0.05 < result.rms_px < 0.2
    assert json.loads((tmp_path / "cam0.json").read_text())["model"] == result.model
    assert (tmp_path / "cam0.html").stat().st_size > 0
    with open_take(stereo_take) as take:
        stored = take.calibration
    assert stored is not None
    np.testing.assert_allclose(stored["cam0"]["K"], result.camera_matrix())
    stages = [u.stage for u in updates]
    assert stages == ["detect"] * 17 + ["calibrate", "write"]  # 16 images searched, then done
    assert [u.done for u in updates[:17]] == list(range(17))
    assert {u.unit for u in updates[:17]} == {"images searched for the board"}


def test_intrinsics_without_the_board_is_a_calibration_error(tmp_path: Path) -> None:
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((100, 100), 128, np.uint8))
    options = IntrinsicsOptions(images=[blank], board=REAL_BOARD, out=tmp_path / "x.yaml")
    with pytest.raises(NoBoardFoundError, match=r"blank\.png"):
        run_intrinsics(options)
    assert not (tmp_path / "x.yaml").exists()


def test_glob_images_in_name_order(tmp_path: Path) -> None:
    for name in ("b2.png", "a10.png", "a9.png"):
        (tmp_path / name).touch()
    assert [p.name for p in glob_images(str(tmp_path / "*.png"))] == ["a10.png", "a9.png", "b2.png"]
    assert glob_images(str(tmp_path / "none*.png")) == []


@pytest.mark.slow
def test_rig_from_image_sets(tmp_path: Path) -> None:
    real_files("left")
    sets = ImageSets(files={side: glob_images(f"{DATA}/{side}*.jpg") for side in ("left", "right")})
    updates: list[ProgressUpdate] = []
    options = RigOptions(
        board=REAL_BOARD,
        source=sets,
        out=tmp_path / "rig.yaml",
        kalibr=tmp_path / "camchain.yaml",
        reference="right",
    )
    calib = run_rig(options, updates.append)
    assert set(calib.intrinsics) == {"left", "right"}
    assert calib.rig.reference == "right"
    assert calib.rig.n_views == 16
    _, t = calib.rig.relative("right", "left")
    assert 0.05 < float(np.linalg.norm(t)) < 0.2
    fs = cv2.FileStorage(str(tmp_path / "rig.yaml"), cv2.FILE_STORAGE_READ)
    assert fs.getNode("cameras").string() == "left,right"
    assert fs.getNode("rig_reference").string() == "right"
    np.testing.assert_allclose(fs.getNode("left_T").mat().ravel(), t)
    fs.release()
    assert (tmp_path / "camchain.yaml").exists()
    per_camera = [(u.stage, u.message) for u in updates if u.done is None or u.done == u.total]
    assert per_camera == [
        ("detect", "left"),
        ("calibrate", "left: choosing and fitting the lens model"),
        ("detect", "right"),
        ("calibrate", "right: choosing and fitting the lens model"),
        ("calibrate", "rig: 2 devices, 16 views"),
        ("write", f"rig -> {tmp_path / 'rig.yaml'}"),
    ]


@pytest.mark.slow
def test_rig_from_a_take_recovers_the_baseline_and_stores_it(stereo_take: Path, tmp_path: Path) -> None:
    options = RigOptions(
        board=BOARD,
        source=TakeSource(path=stereo_take),
        out=tmp_path / "rig.json",
        model="k1k2",
        into_take=stereo_take,
    )
    calib = run_rig(options)
    assert calib.rig.n_views == 12
    R, t = calib.rig.relative("cam0", "cam1")
    rot_deg = float(np.degrees(np.linalg.norm(cv2.Rodrigues(R)[0])))
    assert rot_deg < 0.2, rot_deg
    assert float(np.linalg.norm(t - T1)) < 2e-3, t
    assert json.loads((tmp_path / "rig.json").read_text())["reference"] == "cam0"
    with open_take(stereo_take) as take:
        stored = take.calibration
    assert stored is not None
    np.testing.assert_allclose(stored["cam1"]["t"], t)


@pytest.mark.slow
def test_rig_needs_two_calibrated_devices(tmp_path: Path) -> None:
    sets = ImageSets(files={"left": real_files("left")})
    with pytest.raises(CalibrationError, match="at least 2 cameras"):
        run_rig(RigOptions(board=REAL_BOARD, source=sets, out=tmp_path / "rig.json"))
    assert not (tmp_path / "rig.json").exists()


def test_event_times_at_pulses_or_at_a_rate(tmp_path: Path) -> None:
    path = make_take(tmp_path / "t.h5").path
    with open_take(path) as take:
        frames = take.camera("cam0")
        mid = frames.timestamps_us + frames[0].exposure_us // 2
        span = take.sensor("ev0").span
    np.testing.assert_array_equal(event_times(path, "ev0"), mid)
    at_rate = event_times(path, "ev0", rate_hz=100.0)
    assert span is not None
    assert at_rate[0] == span[0]
    assert set(np.diff(at_rate).tolist()) == {10_000}
    with pytest.raises(RigdError, match="no event sensor 'nope'"):
        event_times(path, "nope")
    with pytest.raises(RigdError, match="must be > 0 Hz"):
        event_times(path, "ev0", rate_hz=0.0)


def test_events_without_a_board_is_a_calibration_error(tmp_path: Path) -> None:
    """Random events show no board: every method fails, the error names them, nothing is written."""
    path = make_take(tmp_path / "t.h5").path
    options = EventsOptions(take=path, sensor="ev0", board=BOARD, out=tmp_path / "ev0.yaml", methods=["hpf"])
    with pytest.raises(CalibrationError, match=r"board .* not found in 8 frames .*scene=board"):
        run_events(options)
    assert not (tmp_path / "ev0.yaml").exists()
