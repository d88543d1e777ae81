# ruff: noqa: N803, N806  (K follows the notation of the calibration literature)
"""e2calib on the sim rig: reconstruction method vs calibration error vs time.

`python -m bench.e2calib [--seconds 4] [--width 640 --height 360] [--threshold 0.3]`

Captures a take of the simulated rig watching the moving chessboard (`scene=board` in every
device spec), reconstructs frames from each event sensor's events at the cameras' mid-exposure
instants with each method of `calibration.e2calib`, calibrates, and prints one row per
(sensor, method): frames used (board found / reconstructed), focal error %, principal point
error px, RMS px and time s (reconstruction + detection + calibration), scored against the
simulator's ground-truth K. The sim is pinhole (no lens distortion); the calibration still fits
k1, k2, as it would on a real lens. Acceptance target for the accurate method (``integrate``):
focal error < 0.5 %, RMS < 0.3 px.

Measured (4 s, 640x360, threshold 0.3, 2 shared cores), focal err % / RMS px / time s:
window 0.8-2.8 / 0.26-0.47 / 10-14, hpf 0.6-2.0 / 0.27 / 2-4, integrate 0.02-0.05 / 0.11 / 2-3.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from pathlib import Path
from typing import Literal

import numpy as np

from calibration.boards import parse_board
from calibration.e2calib import METHODS, E2CalibResult, ReconstructionParams, calibrate_events
from firmware_sim.board_scene import BoardScene
from firmware_sim.scene import REF_FOCAL, REF_WIDTH
from firmware_sim.world import reset_world
from rigd.app.capture import CaptureResult, run_capture
from rigd.app.config import RigConfig, default_sim_rig
from rigd.take.reader import open_take

log = logging.getLogger(__name__)

BOARD = BoardScene().board_spec


def board_rig(
    world: str,
    resolution: tuple[int, int],
    threshold: float | None = None,
    rate_hz: float = 30.0,
    clock: Literal["real", "virtual"] = "real",
    pixel_format: Literal["mono8", "rgb8", "bayer_rg8"] = "mono8",
) -> RigConfig:
    """The built-in sim rig with every device watching the moving board (mono8 frames unless
    `pixel_format` says otherwise).

    `clock="virtual"` runs the sim world on virtual time: the same board poses every run."""
    reset_world(world)
    cfg = default_sim_rig(
        world=world, resolution=resolution, pixel_format=pixel_format, rate_hz=rate_hz, clock=clock
    )
    data = cfg.model_dump()
    for dev in data["cameras"]:
        dev["spec"] += "&scene=board"
    for dev in data["event_sensors"]:
        dev["spec"] += "&scene=board" + (f"&threshold={threshold:g}" if threshold else "")
    return RigConfig.model_validate(data)


def capture_board_take(
    out_dir: Path,
    seconds: float,
    resolution: tuple[int, int] = (640, 360),
    threshold: float | None = None,
    world: str = "e2calib",
    clock: Literal["real", "virtual"] = "real",
    pixel_format: Literal["mono8", "rgb8", "bayer_rg8"] = "mono8",
) -> CaptureResult:
    """Capture a take of the sim rig watching the moving board (`clock="virtual"`: a
    deterministic take, the same for every run whatever the machine's load; the world is reset)."""
    rig = board_rig(world, resolution, threshold, clock=clock, pixel_format=pixel_format)
    return run_capture(rig, out_dir, seconds)


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
        cam = take.frames(take.cameras[0])
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=360)
    ap.add_argument(
        "--threshold", type=float, default=None, help="event contrast threshold (sim default 0.3)"
    )
    ap.add_argument("--take", type=Path, default=None, help="use this take instead of capturing one")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    with tempfile.TemporaryDirectory() as tmp:
        if args.take is None:
            t0 = time.perf_counter()
            cap = capture_board_take(Path(tmp), args.seconds, (args.width, args.height), args.threshold)
            print(
                f"captured {args.seconds:g} s at {args.width}x{args.height} "
                f"in {time.perf_counter() - t0:.1f} s: {cap.events}"
            )
            take_path = cap.path
        else:
            take_path = args.take
        params = ReconstructionParams(contrast=args.threshold or 0.3)
        results = sensor_results(take_path, params=params)
        with open_take(take_path) as take:
            width, height = take.sensor(take.event_sensors[0]).geometry
        K = true_k(width)
        K[1, 2] = height / 2.0
        print(f"e2calib: {take_path.name}, {width}x{height}, board {BOARD}")
        print("frames = board found / reconstructed; time = reconstruct + detect + calibrate")
        print(
            f"{'sensor':6} {'method':9} {'frames':>8} {'focal err %':>11} {'pp err px':>9} "
            f"{'RMS px':>7} {'time s':>7}"
        )
        for res in results.values():
            for r in score(res, K):
                if "rms_px" in r:
                    print(
                        f"{r['sensor']:6} {r['method']:9} {r['frames']:>8} {r['focal_err_pct']:11.3f} "
                        f"{r['pp_err_px']:9.2f} {r['rms_px']:7.3f} {r['time_s']:7.2f}"
                    )
                else:
                    print(f"{r['sensor']:6} {r['method']:9} {r['frames']:>8} {'failed':>11}")


if __name__ == "__main__":
    main()
