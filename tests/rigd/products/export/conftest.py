"""The take every `rigd export` command-line test exports: half a second of the sim rig (3 RGB
cameras, 2 event sensors at 320x180) watching the board, which stores its ground-truth
calibration as it is captured; and the same take without it (as a real rig's take arrives)."""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py
import pytest

from rigd.app.testing.board import capture_board_take

RES = (320, 180)
WORLD = "t-export-cli"


@pytest.fixture(scope="session")
def takes(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(take without calibration, the take as captured: with the simulator's ground truth)."""
    root = tmp_path_factory.mktemp("export-cli")
    cap = capture_board_take(root / "raw", 0.5, RES, world=WORLD, clock="virtual")
    bare = root / "uncalibrated.h5"
    shutil.copy(cap.path, bare)
    with h5py.File(bare, "r+") as f:
        del f["calibration"]
    return bare, cap.path
