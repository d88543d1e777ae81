"""Calibration results stored in a take and read back by training jobs."""

from __future__ import annotations

import uuid
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from reconstruction.dataset import WindowSampler
from rigd.app.capture import run_capture
from rigd.app.cli import app
from rigd.app.config import default_sim_rig
from rigd.core.errors import TakeError
from rigd.take.calibration import GROUND_TRUTH_SOURCE, store_calibration
from rigd.take.reader import Take
from rigd.take.validate import validate_take

pytestmark = pytest.mark.slow

BOARD_IMAGES = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "chessboard-stereo"


@pytest.fixture(scope="module")
def take_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cfg = default_sim_rig(world=f"cal-{uuid.uuid4().hex[:8]}", resolution=(160, 90), pixel_format="mono8")
    cfg.cameras = cfg.cameras[:1]
    return run_capture(cfg, tmp_path_factory.mktemp("take"), 1.0).path


@pytest.mark.skipif(not BOARD_IMAGES.is_dir(), reason=f"shared test data not found at {BOARD_IMAGES}")
def test_calibrate_into_take_then_a_training_job_reads_it(take_path: Path, tmp_path: Path) -> None:
    images = sorted(str(p) for p in BOARD_IMAGES.glob("left*.jpg"))
    r = CliRunner().invoke(
        app,
        [
            "calibrate", "intrinsics", *images, "--board", "chessboard:9x6:0.025",
            "--camera", "cam0", "--out", str(tmp_path / "cam0.yaml"), "--into-take", str(take_path),
        ],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    assert f"stored in {take_path}: /calibration/cam0" in r.output  # --into-take says where
    shown = CliRunner().invoke(app, ["inspect", str(take_path)])
    line = next(x for x in shown.stdout.splitlines() if x.startswith("calibration: cam0 "))
    assert "fx 5" in line  # ~519 px
    assert "RMS 0." in line
    assert "calibrate intrinsics" in line
    as_json = CliRunner().invoke(app, ["inspect", str(take_path), "--json"])
    assert '"calibration": {' in as_json.stdout
    with Take(take_path) as take:
        cal = take.calibration
        assert cal is not None
        # ev0, ev1 keep the simulator's ground truth stored at capture; cam0's is kept beside the result
        assert set(cal) == {"cam0", "ev0", "ev1"}
        assert cal["ev0"]["result"]["source"] == GROUND_TRUTH_SOURCE
        assert "K" in cal["cam0"]["result"]["ground_truth"]["intrinsics"]
        k_mat = cal["cam0"]["K"]
        assert k_mat.shape == (3, 3)
        assert 500 < k_mat[0, 0] < 540  # the real camera's focal length, ~519 px
        assert cal["cam0"]["result"]["intrinsics"]["rms_px"] < 0.25
        sample = next(iter(WindowSampler(take, "ev0", "cam0", window_us=50_000, bins=2, n_samples=1)))
        assert sample.calibration is not None
        np.testing.assert_array_equal(sample.calibration["cam0"]["K"], k_mat)
    assert validate_take(take_path) == []


def test_store_rejects_unknown_devices_and_keeps_the_take(take_path: Path) -> None:
    with pytest.raises(TakeError, match="no camera or event sensor 'cam7'"):
        store_calibration(take_path, "cam7", intrinsics={"K": np.eye(3), "dist": [0.0], "image_size": [1, 1]})
    pose = {"R": np.eye(3).tolist(), "t": [0.1, 0.0, 0.0]}
    store_calibration(take_path, "ev1", pose=pose, source="test")
    store_calibration(take_path, "ev1", pose={"R": np.eye(3).tolist(), "t": [0.2, 0.0, 0.0]}, source="again")
    with Take(take_path) as take:
        assert take.calibration is not None
        np.testing.assert_allclose(take.calibration["ev1"]["t"], [0.2, 0.0, 0.0])
        assert take.calibration["ev1"]["result"]["source"] == "again"
        assert len(take.sensor("ev0").events()) > 0
    shown = CliRunner().invoke(app, ["inspect", str(take_path)]).stdout
    assert "calibration: ev1 pose only, posed in the rig frame (again)" in shown
