# ruff: noqa: N806  (K follows the notation of the calibration literature)
"""A stereo take of a board with known truth: two cameras 10 cm apart along x, one frame each per
trigger pulse, rendered through known intrinsics (`firmware_sim.testing.board_views`)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from calibration.boards import parse_board
from firmware_sim.testing.board_views import SynthCamera, render, view_poses
from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.frames import Frame
from rigd.core.schema import SyncReport
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.take import TakeWriter
from rigd.take.seal import finalize_take

BOARD = "chessboard:9x6:0.03"
SIZE = (320, 240)
K = np.array([[300.0, 0.0, 161.2], [0.0, 299.5, 119.3], [0.0, 0.0, 1.0]])
DIST = np.array([-0.08, 0.03, 0.0, 0.0, 0.0])
#: cam1's pose in the rig frame of cam0: x_cam1 = x_cam0 + T1 (centre 10 cm to the right).
T1 = np.array([-0.10, 0.0, 0.0])
PERIOD_US = 33_333


def stereo_board_take(path: Path, n_views: int = 12) -> Path:
    """Write the take (finalized, identity clocks) and return its path."""
    board = parse_board(BOARD)
    cam = SynthCamera(K, DIST, SIZE)
    poses = view_poses(board, cam, n_views, 0.7, seed=4, max_tilt=35.0, margin_px=55.0)
    w = TakeWriter(
        path,
        rig_config_json='{"name": "stereo"}',
        take_id="stereo-1",
        config=WriterConfig(),
        rigd_version="t",
    )
    w.add_trigger(DeviceInfo(kind="trigger", spec="sim://t/trigger"))
    for name in ("cam0", "cam1"):
        info = DeviceInfo(kind="rgb_camera", spec=f"sim://t/{name}")
        w.add_camera(name, info, (SIZE[1], SIZE[0]), np.uint8, "{}")
    t = 1_000_000 + np.arange(n_views, dtype=np.int64) * PERIOD_US
    for i, (rv, tv) in enumerate(poses):
        R = cv2.Rodrigues(rv)[0]
        for name, tv_cam in (("cam0", tv), ("cam1", tv + T1)):
            rv_cam = np.asarray(cv2.Rodrigues(R)[0], np.float64).ravel()
            img = render(board, cam, rv_cam, tv_cam, noise_dn=1.0, seed=10 * i + len(name))
            w.append_frame(name, Frame(img, int(t[i]), 2000, i, 1000 + i))
    w.append_pulses(PulseBatch(np.arange(n_views, dtype=np.int64), t, t * 1000))
    report = SyncReport(
        rate_hz=30.0, n_pulses=n_views, t_first_pulse_us=int(t[0]), t_last_pulse_us=int(t[-1])
    )
    identity = ClockMap(device_ref_us=0, rig_ref_us=0, rate=1.0, frac_us=0.0)
    index = np.arange(n_views, dtype=np.int64)
    finalize_take(w, {"cam0": identity, "cam1": identity}, {"cam0": index, "cam1": index}, report)
    w.close()
    return path
