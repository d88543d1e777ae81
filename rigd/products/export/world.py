# ruff: noqa: N803, N806  (R, t, A follow the notation of the calibration literature)
"""The world frame of an export (`--world board|cam0|floor`).

Why: rigd calibrates in the rig frame (cam0's camera axes), which is tilted with the rig and has
no floor. Trainers that regularise with a floor (Dynamic3DGaussians penalises foreground points
below y = 0: `clamp(fg_pts[:, 1], min=0)`) need a gravity-aligned world with y down and the floor
at y = 0. The frames:

- `cam0`: the rig frame as stored (x_cam = R x_rig + t of the calibration).
- `board`: the board plane's frame stored with the calibration (a simulated take stores its
  scene's plane: z = 0 the plane, x right, y down, which is gravity-aligned for an upright board).
- `floor`: y along gravity (the board's y when the take stores a board, else the mean of the
  cameras' y axes: cameras stand upright), x along cam0's x made horizontal, origin under the
  board's origin (else cam0's centre), raised so that the floor y = 0 lies at the lowest point
  of the initial point cloud: nothing in the scene is below it.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import NDArray

from rigd.core.errors import TakeError
from rigd.products.export.common import ExportPlan
from rigd.products.export.points import cloud_of

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


def _transform(A: F64, b: F64) -> F64:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = A, b
    return m


def _board(plan: ExportPlan) -> tuple[F64, F64] | None:
    """(R, t) of the board in the rig frame: x_rig = R x_board + t."""
    return plan.take.board_pose


def _gravity_frame(plan: ExportPlan) -> F64:
    """rig -> a gravity-aligned frame (y down), origin at the board's origin or cam0's centre."""
    board = _board(plan)
    if board is not None:
        down, origin = board[0][:, 1], board[1]
    else:
        down = np.mean([c.R.T[:, 1] for c in plan.cameras], axis=0)
        origin = plan.cameras[0].centre
        log.info("--world floor: no board stored; gravity is the mean of the cameras' down axes")
    y = down / np.linalg.norm(down)
    x = plan.cameras[0].R.T[:, 0]
    x = x - y * (x @ y)
    if np.linalg.norm(x) < 1e-6:
        raise TakeError(f"{plan.take.path}: cam0 looks straight along gravity; use --world cam0 or board")
    x /= np.linalg.norm(x)
    z = np.cross(x, y)
    A = np.stack([x, y, z])  # rows: the new axes in rig coordinates
    return _transform(A, -A @ origin)


def _apply(plan: ExportPlan, m: F64) -> None:
    plan.rig_to_world = m @ plan.rig_to_world
    A, b = m[:3, :3], m[:3, 3]
    for c in plan.cameras:
        R_w = c.R @ A.T
        c.R, c.t = R_w, c.t - R_w @ b
    if plan.cloud is not None:
        plan.cloud.xyz = plan.cloud.xyz @ A.T + b


def apply_world(plan: ExportPlan) -> None:
    """Move every camera (and later the point cloud, the event sensors) to `--world`'s frame."""
    kind = plan.options.world_frame
    if kind == "cam0":
        plan.world_note = "cam0: the rig frame of the stored calibration (OpenCV axes of cam0)"
        return
    if kind == "board":
        board = _board(plan)
        if board is None:
            raise TakeError(
                f"{plan.take.path}: --world board needs the board plane's pose in the take (a simulated "
                "take stores it with its ground truth); use --world floor or cam0"
            )
        R, t = board
        _apply(plan, _transform(R.T, -R.T @ t))
        plan.world_note = "board: the board plane's frame (z = 0 the plane, x right, y down)"
        return
    _apply(plan, _gravity_frame(plan))
    cloud = cloud_of(plan)
    floor = float(np.max(cloud.xyz[:, 1]))
    _apply(plan, _transform(np.eye(3), np.array([0.0, -floor, 0.0])))
    plan.world_note = (
        "floor: gravity-aligned (y down), floor y = 0 at the lowest of the "
        f"{len(cloud)} initial points, x along cam0's x"
    )
    log.info("--world floor: floor %.3f m below the origin", floor)
