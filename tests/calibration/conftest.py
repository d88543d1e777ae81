"""Shared fixtures: real stereo data (skipped when missing) and synthetic renders (cached per module)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from calibration.boards import BoardSpec, Detection, detect, parse_board
from calibration.intrinsics import RejectedView, detect_images
from tests.calibration.synth import SynthCamera, render

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "chessboard-stereo"
REAL_BOARD = "chessboard:9x6:0.025"
SYNTH_BOARD = "chessboard:9x6:0.03"


def real_files(side: str) -> list[Path]:
    if not DATA.is_dir():
        pytest.skip(f"real data missing: {DATA}")
    files = sorted(DATA.glob(f"{side}*.jpg"))
    if len(files) < 10:
        pytest.skip(f"real data incomplete: {len(files)} {side} images in {DATA}")
    return files


@pytest.fixture(scope="session")
def real_detections() -> dict[str, tuple[list[Detection], list[RejectedView], list[str]]]:
    board = parse_board(REAL_BOARD)
    return {side: detect_images(real_files(side), board) for side in ("left", "right")}


def view_id(name: str) -> str:
    return re.findall(r"\d+", name)[-1]


def synth_detections(
    board: BoardSpec,
    cam: SynthCamera,
    poses: list[tuple[np.ndarray, np.ndarray]],
    seed: int = 0,
    noise_dn: float = 2.0,
) -> list[Detection]:
    out = []
    for i, (rv, tv) in enumerate(poses):
        d = detect(render(board, cam, rv, tv, noise_dn=noise_dn, seed=seed * 1000 + i), board, f"v{i:02d}")
        assert d is not None, f"synthetic view {i} not detected"
        out.append(d)
    return out
