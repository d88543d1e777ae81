# ruff: noqa: N803, N806  (K, R, t, F, P follow the notation of the calibration literature)
"""A sparse initial point cloud from the calibrated RGB views, for formats that start from one
(Dynamic3DGaussians' init_pt_cld.npz, COLMAP's points3D.bin).

Why triangulate instead of running SfM: the cameras are already calibrated, so matching SIFT
features between every pair of views at a few timesteps, keeping the matches that agree with
the calibrated epipolar geometry, and triangulating with the known projection matrices gives
points in the rig frame directly, in seconds. Matches on repeated texture (a chessboard row lies
along an epipolar line) are dropped by the ratio test and by requiring a small reprojection error
in both views.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from rigd.core.errors import TakeError
from rigd.core.progress import ProgressUpdate
from rigd.products.export.common import ExportPlan

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: Lowe's ratio test threshold and the geometric gates, in output pixels.
RATIO = 0.75
MAX_EPIPOLAR_PX = 1.0
MAX_REPROJ_PX = 1.0


@dataclass
class PointCloud:
    """Triangulated points in the world (rig) frame with their colour and observations."""

    xyz: F64  # (N, 3) metres
    rgb: NDArray[np.uint8]  # (N, 3)
    error_px: F64  # (N,) mean reprojection error over the two views
    views: NDArray[np.int64]  # (N, 3): timestep, camera i, camera j
    uv: F64  # (N, 2, 2): pixel in view i and in view j

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


def _skew(v: F64) -> F64:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def fundamental(Ki: F64, Ri: F64, ti: F64, Kj: F64, Rj: F64, tj: F64) -> F64:
    """F with x_j^T F x_i = 0 for pixels of the same world point in views i and j."""
    R = Rj @ Ri.T
    t = tj - R @ ti
    return np.linalg.inv(Kj).T @ _skew(t) @ R @ np.linalg.inv(Ki)


def _project(P: F64, X: F64) -> F64:
    x = (P @ np.c_[X, np.ones(len(X))].T).T
    return x[:, :2] / x[:, 2:3]


def triangulate(plan: ExportPlan) -> PointCloud:
    """SIFT matches of every camera pair at `point_frames` timesteps, gated and triangulated."""
    cams = plan.cameras
    T = plan.frames.pulses.size
    steps = np.unique(np.linspace(0, T - 1, min(plan.options.point_frames, T)).round().astype(int))
    sift = cv2.SIFT_create(nfeatures=4000)  # type: ignore[attr-defined]
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    P = [c.K @ np.c_[c.R, c.t] for c in cams]
    parts: list[tuple[F64, NDArray[np.uint8], F64, NDArray[np.int64], F64]] = []
    for n, k in enumerate(steps):
        imgs = [plan.image(int(k), j) for j in range(len(cams))]
        feats = [sift.detectAndCompute(cv2.cvtColor(im, cv2.COLOR_RGB2GRAY), None) for im in imgs]
        for i in range(len(cams)):
            for j in range(i + 1, len(cams)):
                (kpi, di), (kpj, dj) = feats[i], feats[j]
                if di is None or dj is None or len(kpi) < 2 or len(kpj) < 2:
                    continue
                pairs = [m for m, m2 in matcher.knnMatch(di, dj, k=2) if m.distance < RATIO * m2.distance]
                if not pairs:
                    continue
                ui = np.array([kpi[m.queryIdx].pt for m in pairs], np.float64)
                uj = np.array([kpj[m.trainIdx].pt for m in pairs], np.float64)
                ci, cj = cams[i], cams[j]
                F = fundamental(ci.K, ci.R, ci.t, cj.K, cj.R, cj.t)
                hi, hj = np.c_[ui, np.ones(len(ui))], np.c_[uj, np.ones(len(uj))]
                lines = hi @ F.T  # epipolar lines in view j
                dist = np.abs(np.sum(lines * hj, axis=1)) / np.hypot(lines[:, 0], lines[:, 1])
                keep = dist < MAX_EPIPOLAR_PX
                if not keep.any():
                    continue
                ui, uj = ui[keep], uj[keep]
                Xh = cv2.triangulatePoints(P[i], P[j], ui.T, uj.T)
                X = (Xh[:3] / Xh[3]).T
                zi = (X @ ci.R.T + ci.t)[:, 2]
                zj = (X @ cj.R.T + cj.t)[:, 2]
                err = 0.5 * (
                    np.linalg.norm(_project(P[i], X) - ui, axis=1)
                    + np.linalg.norm(_project(P[j], X) - uj, axis=1)
                )
                ok = (zi > 0) & (zj > 0) & (err < MAX_REPROJ_PX) & np.isfinite(X).all(axis=1)
                px = np.clip(np.round(ui[ok]).astype(int), 0, [ci.size[0] - 1, ci.size[1] - 1])
                rgb = imgs[i][px[:, 1], px[:, 0]]
                views = np.tile(np.array([k, i, j], np.int64), (int(ok.sum()), 1))
                parts.append((X[ok], rgb, err[ok], views, np.stack([ui[ok], uj[ok]], axis=1)))
        plan.progress(ProgressUpdate("points", f"timestep {n + 1}/{steps.size}", n + 1, int(steps.size)))
    if not parts or sum(len(p[0]) for p in parts) == 0:
        raise TakeError(
            f"{plan.take.path}: no feature matched across the calibrated views at {steps.size} timesteps; "
            "cannot triangulate an initial point cloud (is the scene textured and the calibration right?)"
        )
    cloud = PointCloud(
        xyz=np.concatenate([p[0] for p in parts]),
        rgb=np.concatenate([p[1] for p in parts]).astype(np.uint8),
        error_px=np.concatenate([p[2] for p in parts]),
        views=np.concatenate([p[3] for p in parts]),
        uv=np.concatenate([p[4] for p in parts]),
    )
    log.info(
        "triangulated %d points (median reprojection %.3f px)", len(cloud), float(np.median(cloud.error_px))
    )
    return cloud


def cloud_of(plan: ExportPlan) -> PointCloud:
    """The plan's point cloud in its world, triangulated once (formats and --world floor share it)."""
    if plan.cloud is None:
        plan.cloud = triangulate(plan)
    assert isinstance(plan.cloud, PointCloud)
    return plan.cloud


def write_ply(cloud: PointCloud, path: Path) -> None:
    """Binary little-endian PLY with x y z (float) and red green blue (uchar): what open3d and
    plyfile read (nerfstudio's `ply_file_path`, 4DGaussians' `fetchPly`)."""
    rows = np.zeros(
        len(cloud), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")]
    )
    rows["x"], rows["y"], rows["z"] = cloud.xyz.T
    rows["r"], rows["g"], rows["b"] = cloud.rgb.T
    head = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(cloud)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    path.write_bytes(head.encode() + rows.tobytes())
