# ruff: noqa: N803, N806  (R follows the notation of the calibration literature)
"""COLMAP sparse model of the calibrated rig, one registered image per (timestep, camera).

    sparse/0/cameras.bin   one PINHOLE camera per rig camera (fx, fy, cx, cy of the new K, in
                           COLMAP's pixels: pixel (0, 0) centred at (0.5, 0.5), cx = rigd's + 0.5)
    sparse/0/images.bin    image per frame: qvec/tvec world -> camera (OpenCV axes, the rig frame),
                           name <cam>/<t:06d>.jpg, its 2-D observations of the points
    sparse/0/points3D.bin  the triangulated initial point cloud with its two-view tracks
    images/<cam>/<t:06d>.jpg
    times.json             per image name: t_us (mid-exposure, rig us), time in [0, 1], split

4DGaussians reads `--format 4dgaussians` (its PanopticSports reader, one K per camera): given
this directory, its `Scene` sees `sparse/` and takes the plain COLMAP reader, which has no time.

Binary layout as COLMAP's src/colmap/scene/reconstruction_io.cc writes it (little endian):
cameras: u64 n, then u32 id, i32 model, u64 width, u64 height, f64 params[]; images: u64 n, then
u32 id, f64 qw qx qy qz, f64 tx ty tz, u32 camera_id, name NUL-terminated, u64 n2d, then per 2-D
point f64 x, f64 y, i64 point3D_id (-1: none); points3D: u64 n, then u64 id, f64 xyz, u8 rgb,
f64 error, u64 track length, then per element u32 image_id, u32 point2D_idx.
"""

from __future__ import annotations

import json
import logging
import struct
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from rigd.products.export.common import PIXEL_CENTRE, ExportPlan, K_at
from rigd.products.export.points import PointCloud, cloud_of

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: COLMAP's model id of PINHOLE (fx, fy, cx, cy).
PINHOLE = 1


def rotmat_to_qvec(R: F64) -> F64:
    """(w, x, y, z) unit quaternion of a rotation matrix, w >= 0 (COLMAP's order and sign)."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(R, np.float64)).as_quat()
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q


def image_name(plan: ExportPlan, k: int, j: int) -> str:
    return f"{plan.cameras[j].name}/{k:06d}.jpg"


def _write_cameras(plan: ExportPlan, dest: Path) -> None:
    with (dest / "cameras.bin").open("wb") as f:
        f.write(struct.pack("<Q", len(plan.cameras)))
        for j, c in enumerate(plan.cameras):
            f.write(struct.pack("<IiQQ", j + 1, PINHOLE, c.size[0], c.size[1]))
            K = K_at(c.K, PIXEL_CENTRE["colmap"])
            f.write(struct.pack("<4d", K[0, 0], K[1, 1], K[0, 2], K[1, 2]))


def _write_points(cloud: PointCloud, path: Path, tracks: NDArray[np.int64] | None) -> None:
    """points3D.bin; tracks (N, 2, 2) of (image_id, point2D_idx) per observation, or none."""
    with path.open("wb") as f:
        f.write(struct.pack("<Q", len(cloud)))
        for p in range(len(cloud)):
            f.write(struct.pack("<Q3d3Bd", p + 1, *cloud.xyz[p], *cloud.rgb[p], cloud.error_px[p]))
            if tracks is None:
                f.write(struct.pack("<Q", 0))
            else:
                f.write(struct.pack("<Q", 2) + tracks[p].astype("<u4").tobytes())


def write_model(plan: ExportPlan, cloud: PointCloud, dest: Path) -> None:
    """cameras.bin, images.bin and points3D.bin of the plan's frames and the cloud."""
    cams, fr = plan.cameras, plan.frames
    C, T = len(cams), fr.pulses.size
    dest.mkdir(parents=True, exist_ok=True)
    _write_cameras(plan, dest)
    # Each point is seen in two images of one timestep: (k, i) and (k, j).
    n = len(cloud)
    v = cloud.views
    obs_image = np.concatenate([v[:, 0] * C + v[:, 1], v[:, 0] * C + v[:, 2]])
    # COLMAP's pixel (0, 0) is centred at (0.5, 0.5); the matches are in rigd's pixels.
    obs_uv = np.concatenate([cloud.uv[:, 0], cloud.uv[:, 1]]) + PIXEL_CENTRE["colmap"]
    obs_point = np.concatenate([np.arange(n), np.arange(n)])
    order = np.argsort(obs_image, kind="stable")
    starts = np.searchsorted(obs_image[order], np.arange(T * C + 1))
    point2d_idx = np.empty(2 * n, np.int64)  # index of each observation within its image
    point2d_idx[order] = np.arange(2 * n) - starts[obs_image[order]]
    with (dest / "images.bin").open("wb") as f:
        f.write(struct.pack("<Q", T * C))
        for k in range(T):
            for j, c in enumerate(cams):
                img = k * C + j
                f.write(struct.pack("<I4d3dI", img + 1, *rotmat_to_qvec(c.R), *c.t, j + 1))
                f.write(image_name(plan, k, j).encode() + b"\0")
                sel = order[starts[img] : starts[img + 1]]
                f.write(struct.pack("<Q", sel.size))
                rows = np.zeros(sel.size, dtype=[("x", "<f8"), ("y", "<f8"), ("id", "<i8")])
                rows["x"], rows["y"], rows["id"] = obs_uv[sel, 0], obs_uv[sel, 1], obs_point[sel] + 1
                f.write(rows.tobytes())
    tracks = np.stack([obs_image + 1, point2d_idx], axis=1).reshape(2, n, 2).transpose(1, 0, 2)
    _write_points(cloud, dest / "points3D.bin", tracks)


def write(plan: ExportPlan) -> None:
    fr = plan.frames
    plan.write_images(lambda k, j: f"images/{image_name(plan, k, j)}")
    cloud = cloud_of(plan)
    write_model(plan, cloud, plan.out / "sparse" / "0")
    time01 = fr.time01()
    train = plan.train_mask
    times = {
        image_name(plan, k, j): {
            "t_us": int(fr.t_us[k, j]),
            "time": float(time01[k, j]),
            "timestep": k,
            "split": "train" if train[k, j] else "test",
        }
        for k in range(fr.pulses.size)
        for j in range(len(plan.cameras))
    }
    (plan.out / "times.json").write_text(json.dumps(times, indent=1))
    log.info("colmap: %d images, %d points", fr.pulses.size * len(plan.cameras), len(cloud))
