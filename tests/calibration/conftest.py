"""Shared fixtures: detections in the real stereo data (skipped when missing)."""

from __future__ import annotations

import pytest

from calibration.boards import Detection, parse_board
from calibration.intrinsics import RejectedView, detect_images
from tests.calibration.real_data import REAL_BOARD, real_files


@pytest.fixture(scope="session")
def real_detections() -> dict[str, tuple[list[Detection], list[RejectedView], list[str]]]:
    board = parse_board(REAL_BOARD)
    return {side: detect_images(real_files(side), board) for side in ("left", "right")}
