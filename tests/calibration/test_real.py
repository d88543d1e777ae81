# ruff: noqa: N806  (K, R, T follow the notation of the calibration literature)
"""Real 640x512 stereo pair (../shared/data/chessboard-stereo): compare with plain OpenCV."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.boards import parse_board
from calibration.extrinsics import calibrate_rig
from calibration.intrinsics import calibrate_intrinsics
from tests.calibration.real_data import REAL_BOARD, real_files, view_id

pytestmark = pytest.mark.slow


def plain_opencv(side: str) -> tuple[float, np.ndarray, np.ndarray]:
    """findChessboardCorners + cornerSubPix(11x11) + calibrateCamera (5-parameter model)."""
    objp = parse_board(REAL_BOARD).object_points().astype(np.float32)
    obj, img = [], []
    size = (0, 0)
    for f in real_files(side):
        g = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        size = (g.shape[1], g.shape[0])
        ok, c = cv2.findChessboardCorners(g, (9, 6))
        assert ok, f
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
        obj.append(objp)
        img.append(cv2.cornerSubPix(g, c, (11, 11), (-1, -1), crit))
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, size, None, None)
    return float(rms), K, dist.ravel()


@pytest.mark.parametrize("side", ["left", "right"])
def test_real_rms_no_worse_than_opencv_and_intrinsics_agree(side: str, real_detections) -> None:
    dets, rej, warn = real_detections[side]
    assert len(dets) == 16
    assert not rej
    res = calibrate_intrinsics(dets, parse_board(REAL_BOARD), camera=side, rejected=rej, warnings=warn)
    cv_rms, K, _ = plain_opencv(side)
    assert len(res.views) == 16, res.rejected  # same views as OpenCV
    assert res.rms_px <= cv_rms, (res.rms_px, cv_rms)
    assert 0.05 < res.rms_px < 0.2
    ours = res.camera_matrix()
    for name, a, b in [("fx", ours[0, 0], K[0, 0]), ("fy", ours[1, 1], K[1, 1])]:
        assert abs(a - b) < 3 * res.std_devs[name], (name, a, b, res.std_devs[name])
    # Same lens model as plain OpenCV: all four intrinsics agree within the uncertainty
    # (with a different model the principal point legitimately moves with the tangential terms).
    same = calibrate_intrinsics(dets, parse_board(REAL_BOARD), camera=side, model="k1k2k3+tangential")
    Ks = same.camera_matrix()
    for name, a, b in [
        ("fx", Ks[0, 0], K[0, 0]),
        ("fy", Ks[1, 1], K[1, 1]),
        ("cx", Ks[0, 2], K[0, 2]),
        ("cy", Ks[1, 2], K[1, 2]),
    ]:
        assert abs(a - b) < 3 * same.std_devs[name], (name, a, b, same.std_devs[name])
    assert same.rms_px <= cv_rms


def test_real_stereo_extrinsics(real_detections) -> None:
    board = parse_board(REAL_BOARD)
    intr = {s: calibrate_intrinsics(real_detections[s][0], board, camera=s) for s in ("left", "right")}
    views: dict[str, dict] = {}
    for s in ("left", "right"):
        for d in real_detections[s][0]:
            views.setdefault(view_id(d.name), {})[s] = d
    rig = calibrate_rig(intr, views, board)
    R, t = rig.relative("left", "right")
    # Reference: cv2.stereoCalibrate with the same (fixed) intrinsics.
    keys = sorted(views)
    L = [views[k]["left"] for k in keys]
    Rr = [views[k]["right"] for k in keys]
    out = cv2.stereoCalibrate(
        [d.object_points.astype(np.float32) for d in L],
        [d.image_points.astype(np.float32) for d in L],
        [d.image_points.astype(np.float32) for d in Rr],
        intr["left"].camera_matrix(),
        intr["left"].dist_coeffs(),
        intr["right"].camera_matrix(),
        intr["right"].dist_coeffs(),
        (640, 512),
        flags=cv2.CALIB_FIX_INTRINSIC,
    )
    R_cv, t_cv = out[5], out[6].ravel()
    baseline = float(np.linalg.norm(t))
    assert 0.05 < baseline < 0.2  # hand-held stereo pair: about 10 cm
    assert abs(t[0]) > 0.9 * baseline  # side by side along x
    angle = np.degrees(np.arccos(np.clip((np.trace(R.T @ R_cv) - 1) / 2, -1, 1)))
    assert angle < 0.01
    assert np.linalg.norm(t - t_cv) < 1e-4
    cam = rig.cameras[1]
    # Sigmas include each camera's intrinsic uncertainty (16 hand-held views): honest, not tiny.
    assert all(0 < s < 0.2 for s in cam.rot_std_deg)
    assert all(0 < s < 5e-3 for s in cam.t_std_m)
    assert rig.rms_px < 0.25
