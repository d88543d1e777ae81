"""The take every `rigd export` command-line test exports: half a second of the sim rig (3 RGB
cameras, 2 event sensors at 320x180) watching the board, with the ground-truth calibration stored."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from bench.e2calib import capture_board_take
from firmware_sim.board_scene import BoardScene
from firmware_sim.world import get_world
from rigd.take.calibration import store_calibration
from rigd.take.reader import open_take

RES = (320, 180)
WORLD = "t-export-cli"


@pytest.fixture(scope="session")
def takes(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(uncalibrated take, the same take with the ground-truth calibration stored)."""
    root = tmp_path_factory.mktemp("export-cli")
    cap = capture_board_take(root / "raw", 0.5, RES, world=WORLD, clock="virtual")
    scene = get_world(WORLD).resource("scene", BoardScene)
    assert isinstance(scene, BoardScene)
    calibrated = root / "calibrated.h5"
    shutil.copy(cap.path, calibrated)
    with open_take(calibrated) as tk:
        devices = tk.cameras + tk.event_sensors
    for d in devices:
        K, R, t = scene.view_camera(d, *RES)  # noqa: N806
        intr = {"K": K.tolist(), "dist": [0.0] * 5, "image_size": list(RES)}
        store_calibration(calibrated, d, intr, {"R": R.tolist(), "t": t.tolist()})
    return cap.path, calibrated
