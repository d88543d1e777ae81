# ruff: noqa: N803, N806  (K, R, T follow the notation of the calibration literature)
"""Synthetic ground truth: boards rendered through known K, distortion and poses with pixel noise."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from calibration.boards import parse_board
from calibration.extrinsics import calibrate_rig
from calibration.intrinsics import calibrate_intrinsics
from firmware_sim.testing.board_views import SYNTH_BOARD, SynthCamera, synth_detections, view_poses

pytestmark = pytest.mark.slow

K0 = np.array([[600.0, 0.0, 322.3], [0.0, 598.5, 241.7], [0.0, 0.0, 1.0]])
SIMPLE = np.array([-0.12, 0.05, 0.0, 0.0, 0.0])
#: Strong barrel distortion from a decentred wide-angle lens: needs tangential terms and k3.
STRONG = np.array([-0.38, 0.20, 0.004, -0.003, -0.06])


def _check_intrinsics(res, K: np.ndarray) -> None:
    est = res.camera_matrix()
    for name, i, j in [("fx", 0, 0), ("fy", 1, 1)]:
        err = est[i, j] - K[i, j]
        assert abs(err) / K[i, j] < 1e-3, (name, err)
        assert abs(err) < 3 * res.std_devs[name], (name, err, res.std_devs[name])
    for name, i in [("cx", 0), ("cy", 1)]:
        err = est[i, 2] - K[i, 2]
        assert abs(err) < 0.5, (name, err)
        assert abs(err) < 3 * res.std_devs[name], (name, err, res.std_devs[name])


def test_simple_lens_recovered_and_simple_model_chosen() -> None:
    board = parse_board(SYNTH_BOARD)
    cam = SynthCamera(K0, SIMPLE)
    dets = synth_detections(board, cam, view_poses(board, cam, 20, 0.5, seed=1), seed=1)
    res = calibrate_intrinsics(dets, board, camera="synth")
    assert res.model == "k1k2", res.model_scores
    _check_intrinsics(res, K0)
    assert res.rms_px < 0.1
    assert not res.rejected
    assert not res.warnings


def test_strong_distortion_picks_richer_model_with_warning() -> None:
    board = parse_board(SYNTH_BOARD)
    cam = SynthCamera(K0, STRONG)
    dets = synth_detections(board, cam, view_poses(board, cam, 20, 0.45, seed=2), seed=2)
    res = calibrate_intrinsics(dets, board, camera="wide")
    assert res.model != "k1k2", res.model_scores
    chosen = next(s for s in res.model_scores if s.model == res.model)
    simple = next(s for s in res.model_scores if s.model == "k1k2")
    assert chosen.cv_rms_px is not None
    assert simple.cv_rms_px is not None
    assert chosen.cv_rms_px < simple.cv_rms_px
    _check_intrinsics(res, K0)
    assert any("strong distortion" in w for w in res.warnings)


def test_outlier_view_rejected_with_reason() -> None:
    board = parse_board(SYNTH_BOARD)
    cam = SynthCamera(K0, SIMPLE)
    dets = synth_detections(board, cam, view_poses(board, cam, 12, 0.5, seed=3), seed=3)
    bad = dets[4]
    bad.image_points = bad.image_points + np.random.default_rng(0).normal(0, 1.5, bad.image_points.shape)
    res = calibrate_intrinsics(dets, board, camera="synth")
    assert [r.name for r in res.rejected] == [bad.name]
    assert "RMS" in res.rejected[0].reason
    assert "limit" in res.rejected[0].reason
    _check_intrinsics(res, K0)


def _look_at(
    center: list[float], target: tuple[float, float, float] = (0.0, 0.0, 1.0)
) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of a camera at `center` (rig frame) looking at `target`, image y down."""
    c = np.asarray(center, np.float64)
    f = np.asarray(target) - c
    f /= np.linalg.norm(f)
    x = np.cross([0.0, 1.0, 0.0], f)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(f, x), f])
    return R, -R @ c


@pytest.mark.slow
def test_rig_extrinsics_ground_truth() -> None:
    """3 cameras, board at about 1 m: rotation < 0.05 deg, translation < 1 mm, errors within 3 sigma."""
    board = parse_board("chessboard:9x6:0.06")
    gt = {
        "cam0": (np.eye(3), np.zeros(3)),
        "cam1": _look_at([0.30, 0.0, 0.02]),
        "cam2": _look_at([-0.25, 0.04, 0.0]),
    }
    dists = {
        "cam0": SIMPLE,
        "cam1": np.array([-0.10, 0.03, 0, 0, 0]),
        "cam2": np.array([-0.15, 0.08, 0, 0, 0]),
    }
    cams = {c: SynthCamera(K0, dists[c]) for c in gt}
    poses0 = view_poses(board, cams["cam0"], 24, 1.0, seed=5, max_tilt=35.0, margin_px=60.0)
    from calibration.boards import detect
    from firmware_sim.testing.board_views import render

    views: dict[str, dict] = {}
    per_cam: dict[str, list] = {c: [] for c in gt}
    for i, (rv, tv) in enumerate(poses0):
        R0b = cv2.Rodrigues(rv)[0]
        for c, (Rc, tc) in gt.items():
            rvc = cv2.Rodrigues(Rc @ R0b)[0].ravel()
            tvc = Rc @ tv + tc
            d = detect(render(board, cams[c], rvc, tvc, seed=100 * i + len(c)), board, f"{c}-{i:02d}")
            if d is not None:
                per_cam[c].append(d)
                views.setdefault(str(i), {})[c] = d
    assert all(len(v) >= 12 for v in per_cam.values()), {c: len(v) for c, v in per_cam.items()}
    intr = {c: calibrate_intrinsics(per_cam[c], board, camera=c) for c in gt}
    rig = calibrate_rig(intr, views, board)
    assert rig.overlaps == {"cam0": ["cam1", "cam2"], "cam1": ["cam0", "cam2"], "cam2": ["cam0", "cam1"]}
    for c in ("cam1", "cam2"):
        R, t = rig.pose(c)
        Rg, tg = gt[c]
        rot_err = cv2.Rodrigues(R @ Rg.T)[0].ravel()
        assert math.degrees(float(np.linalg.norm(rot_err))) < 0.05, (c, np.degrees(rot_err))
        assert float(np.linalg.norm(t - tg)) < 1e-3, (c, t - tg)
        pose = next(p for p in rig.cameras if p.camera == c)
        assert (np.abs(t - tg) < 3 * np.asarray(pose.t_std_m)).all(), (c, t - tg, pose.t_std_m)
        rot_std = np.radians(np.asarray(pose.rot_std_deg))
        assert (np.abs(rot_err) < 3 * rot_std).all(), (c, rot_err, rot_std)
    assert rig.rms_px < 0.1
