# ruff: noqa: N803, N806  (K follows the notation of the calibration literature)
"""The sim's moving calibration board as ground truth: its board spec, the true intrinsics of
every sim view, and e2calib run on a take of it and scored against that truth (the e2calib
tests and `bench.e2calib`). Takes of the board are captured by `rigd.app.testing.board`."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from calibration.boards import parse_board
from calibration.e2calib import METHODS, E2CalibResult, ReconstructionParams, calibrate_events
from firmware_sim.board_scene import BoardScene
from firmware_sim.scene import REF_FOCAL, REF_WIDTH
from firmware_sim.world import get_world
from firmware_sim.world import reset_world as reset_world  # rigd.app.testing resets a board's world
from rigd.take.reader import open_take

BOARD = BoardScene().board_spec


def true_k(width: int) -> np.ndarray:
    """Ground-truth K of every sim view at a resolution (the sim's pinhole, centre at w/2, h/2)."""
    f = REF_FOCAL * width / REF_WIDTH
    return np.array([[f, 0, width / 2.0], [0, f, 0.0], [0, 0, 1]])


def score(res: E2CalibResult, K_true: np.ndarray) -> list[dict[str, object]]:
    """One table row per method: error of the focal lengths (worse of fx, fy) and principal point."""
    rows: list[dict[str, object]] = []
    for m in res.methods:
        row: dict[str, object] = {
            "sensor": res.sensor,
            "method": m.method,
            "frames": f"{m.detected}/{m.frames}",
            "time_s": m.total_s,
        }
        if m.intrinsics is not None:
            K = m.intrinsics.camera_matrix()
            row["focal_err_pct"] = 100 * max(abs(K[0, 0] / K_true[0, 0] - 1), abs(K[1, 1] / K_true[1, 1] - 1))
            row["pp_err_px"] = float(np.hypot(K[0, 2] - K_true[0, 2], K[1, 2] - K_true[1, 2]))
            row["rms_px"] = m.intrinsics.rms_px
        rows.append(row)
    return rows


def sensor_results(
    take_path: Path, board: str = BOARD, params: ReconstructionParams | None = None
) -> dict[str, E2CalibResult]:
    """Calibrate every event sensor of a take with every method, at the cameras' mid-exposures."""
    spec = parse_board(board)
    out: dict[str, E2CalibResult] = {}
    with open_take(take_path) as take:
        cam = take.camera(take.cameras[0])
        times = cam.timestamps_us + cam[0].exposure_us // 2
        for sensor in take.event_sensors:
            out[sensor] = calibrate_events(
                take.sensor(sensor).events(),
                take.sensor(sensor).geometry,
                times,
                spec,
                sensor=sensor,
                methods=METHODS,
                params=params,
            )
    return out


def true_mid_exposures(take: Path, world: str) -> dict[str, dict[int, float]]:
    """Per camera, the rig mid-exposure time (us) of every frame of a take of `world` -> the
    simulator's true mid-exposure time: what a consumer's pose at that frame should match."""
    rows = get_world(world).truth.frames
    out: dict[str, dict[int, float]] = {}
    with open_take(take) as tk, h5py.File(take, "r") as f:
        for cam in tk.cameras:
            start = {int(c): t for c, t, ok in rows[cam] if ok}
            counters = f[f"frames/{cam}/frame_counter"][()]
            exp = f[f"frames/{cam}/exposure_us"][()]
            mid = tk.camera(cam).timestamps_us + exp // 2
            out[cam] = {
                int(m): start[int(c)] + float(e) / 2 for m, c, e in zip(mid, counters, exp, strict=True)
            }
    return out
