"""The real stereo chessboard recordings (`shared/data/chessboard-stereo` beside the checkout):
their files, or a skip when they are not there."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "chessboard-stereo"
REAL_BOARD = "chessboard:9x6:0.025"


def real_files(side: str) -> list[Path]:
    if not DATA.is_dir():
        pytest.skip(f"real data missing: {DATA}")
    files = sorted(DATA.glob(f"{side}*.jpg"))
    if len(files) < 10:
        pytest.skip(f"real data incomplete: {len(files)} {side} images in {DATA}")
    return files


def view_id(name: str) -> str:
    return re.findall(r"\d+", name)[-1]
