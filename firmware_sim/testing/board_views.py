# ruff: noqa: N806  (K, R, T follow the notation of the calibration literature)
"""Synthetic ground truth for calibration tests: board images rendered through a known camera.

Each output pixel is traced back through the lens (iterative undistortion of the pixel grid, at
2x supersampling) to the board plane and samples a high-resolution board texture; the 2x image is
then area-averaged, blurred slightly like optics and given Gaussian pixel noise. So detections
carry realistic sub-pixel errors while K, distortion and poses are known exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.boards import BoardSpec, Detection, board_image_origin, detect, render_board

F64 = NDArray[np.float64]
_PX_PER_SQUARE = 60
_SS = 2


@dataclass
class SynthCamera:
    K: F64
    dist: F64
    size: tuple[int, int] = (640, 480)
    _rays: F64 | None = field(default=None, repr=False)

    def rays(self) -> F64:
        """Normalised undistorted coordinates (x, y) of the supersampled pixel grid, cached."""
        if self._rays is None:
            w, h = self.size
            ys, xs = np.mgrid[0 : h * _SS, 0 : w * _SS].astype(np.float64)
            pts = np.stack([(xs + 0.5) / _SS - 0.5, (ys + 0.5) / _SS - 0.5], -1).reshape(-1, 1, 2)
            crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
            und = cv2.undistortPoints(pts, self.K, self.dist, R=None, P=None, criteria=crit)
            self._rays = np.asarray(und, np.float64).reshape(h * _SS, w * _SS, 2)
        return self._rays


def look_at(
    board: BoardSpec, center_cam: F64, tilt_deg: float, tilt_axis_deg: float, roll_deg: float = 0.0
) -> tuple[F64, F64]:
    """(rvec, tvec) of a board whose centre is at `center_cam` (camera frame, m), facing the camera
    and tilted by tilt_deg about an in-plane axis at tilt_axis_deg."""
    a = math.radians(tilt_axis_deg)
    axis = np.array([math.cos(a), math.sin(a), 0.0]) * math.radians(tilt_deg)
    R = cv2.Rodrigues(axis)[0] @ cv2.Rodrigues(np.array([0.0, 0.0, math.radians(roll_deg)]))[0]
    c, r = board.inner_corners
    mid = np.array([(c - 1) * board.square_m / 2, (r - 1) * board.square_m / 2, 0.0])
    t = np.asarray(center_cam, np.float64) - R @ mid
    return np.asarray(cv2.Rodrigues(R)[0], np.float64).ravel(), t


def render(
    board: BoardSpec,
    cam: SynthCamera,
    rvec: F64,
    tvec: F64,
    noise_dn: float = 2.0,
    seed: int = 0,
    blur_sigma_px: float = 0.6,
) -> NDArray[np.uint8]:
    """Gray image of the board at pose (rvec, tvec) seen by `cam` (grey background)."""
    tex = render_board(board, _PX_PER_SQUARE, margin_squares=1.0).astype(np.float32)
    origin = board_image_origin(board, _PX_PER_SQUARE, 1.0)
    R = cv2.Rodrigues(np.asarray(rvec, np.float64))[0]
    H = np.column_stack([R[:, 0], R[:, 1], np.asarray(tvec, np.float64)])
    Hi = np.linalg.inv(H)
    rays = cam.rays()
    xyz = rays[..., 0:1] * Hi[:, 0] + rays[..., 1:2] * Hi[:, 1] + Hi[:, 2]
    bx, by = xyz[..., 0] / xyz[..., 2], xyz[..., 1] / xyz[..., 2]
    scale = _PX_PER_SQUARE / board.square_m
    mapx = (origin + bx * scale).astype(np.float32)
    mapy = (origin + by * scale).astype(np.float32)
    big = cv2.remap(tex, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=128)
    w, h = cam.size
    img = cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA)
    if blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
    img = img * 0.8 + 25  # black 25 DN, white 229 DN: not saturated
    rng = np.random.default_rng(seed)
    img = img + rng.normal(0.0, noise_dn, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def view_poses(
    board: BoardSpec,
    cam: SynthCamera,
    n: int,
    depth: float,
    seed: int = 0,
    max_tilt: float = 40.0,
    margin_px: float = 12.0,
) -> list[tuple[F64, F64]]:
    """n varied board poses at about `depth` metres, tilted 15..max_tilt deg, spread over the
    image (borders and corners too) with the whole board, margin included, inside the image."""
    rng = np.random.default_rng(seed)
    c, r = board.inner_corners
    sq = board.square_m
    outline = np.array([[-sq, -sq, 0], [c * sq, -sq, 0], [c * sq, r * sq, 0], [-sq, r * sq, 0]], np.float64)
    w, h = cam.size
    out: list[tuple[F64, F64]] = []
    for _ in range(200 * n):
        if len(out) == n:
            break
        z = depth * rng.uniform(0.85, 1.15)
        half = z * 0.5 * w / cam.K[0, 0]
        x, y = rng.uniform(-half, half), rng.uniform(-half * h / w, half * h / w)
        pose = look_at(
            board, np.array([x, y, z]), rng.uniform(15, max_tilt), rng.uniform(0, 360), rng.uniform(-20, 20)
        )
        p, _ = cv2.projectPoints(outline, pose[0], pose[1], cam.K, cam.dist)
        p = p.reshape(-1, 2)
        if (
            (p.min(axis=0) >= margin_px).all()
            and (p[:, 0] <= w - 1 - margin_px).all()
            and (p[:, 1] <= h - 1 - margin_px).all()
        ):
            out.append(pose)
    assert len(out) == n, "could not place the board; lower depth spread or board size"
    return out


#: The board of the synthetic calibration tests.
SYNTH_BOARD = "chessboard:9x6:0.03"


def synth_detections(
    board: BoardSpec,
    cam: SynthCamera,
    poses: list[tuple[np.ndarray, np.ndarray]],
    seed: int = 0,
    noise_dn: float = 2.0,
) -> list[Detection]:
    """The board detected in each rendered view (every view must show it)."""
    out = []
    for i, (rv, tv) in enumerate(poses):
        d = detect(render(board, cam, rv, tv, noise_dn=noise_dn, seed=seed * 1000 + i), board, f"v{i:02d}")
        assert d is not None, f"synthetic view {i} not detected"
        out.append(d)
    return out
