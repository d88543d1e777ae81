"""Folders of frames for `rigd simulate-events` (its folder input)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


def make_folder(tmp_path: Path, n: int = 5) -> Path:
    """`tmp_path/frames`: n PNG frames of a blurred texture panning 3 px a frame."""
    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (40, 200)).astype(np.float32), (0, 0), 2.0)
    tex = np.clip((tex - tex.mean()) * 5 + 128, 0, 255).astype(np.uint8)
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(n):
        cv2.imwrite(str(folder / f"f{i:03d}.png"), np.ascontiguousarray(tex[:, 3 * i : 3 * i + 60]))
    return folder
