# ruff: noqa: N806  (K follows the notation of the calibration literature)
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

from calibration.e2calib import ReconstructionParams
from firmware_sim.testing.board import BOARD, score, sensor_results, true_k
from rigd.app.testing.board import capture_board_take
from rigd.take.reader import open_take


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
