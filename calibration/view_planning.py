# ruff: noqa: N803, N806  (K, R, J follow the notation of the calibration literature)
"""Where a guided calibration asks for the board next: coverage bins and the next-view choice.

Coverage is counted in bins = (image grid cell of the board centre) x (tilt bin: facing the
camera, or turned about the vertical / horizontal axis with one edge away from the camera).

The next view is chosen by the *information-matrix* method, not a heuristic. For every bin (all
cells x tilt bins) a board pose is synthesised there (at the median depth of the kept views,
tilted ~30 deg for a tilt bin, pushed inside the image) with the current intrinsics; the Jacobian
of its reprojection w.r.t. intrinsics and its own pose (cv2.projectPoints) gives its information
on the intrinsics after eliminating the pose (Schur complement). Kept views contribute the same way
at their estimated poses, plus a weak prior so the matrix is invertible before any view. The hint
is the bin whose addition minimises trace(Cov[fx, fy, cx, cy]). About 45 candidates of ~50
corners cost a few ms, and it runs only after a capture, so no heuristic fallback is needed;
the "emptiest" method (fewest views, corners of the image first) is kept for comparison.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.boards import BoardSpec
from calibration.lens_models import DIST_NAMES, LensModel

F64 = NDArray[np.float64]

#: Tilt bins: facing the camera, or turned ~TILT_DEG about an image axis with one edge away.
TILT_BINS: tuple[str, ...] = ("facing", "right-away", "left-away", "bottom-away", "top-away")
#: Tilt (deg) of the synthesised candidate views of the tilt bins.
TILT_DEG = 30.0
#: Boards tilted less than this (about both axes) count as facing the camera.
FLAT_DEG = 15.0
#: Pixel noise assumed for the hint's information matrix before a calibration measured it.
_DEFAULT_NOISE_PX = 0.3


@dataclass
class Candidate:
    """A bin (grid cell, tilt bin) proposed as the next view, with its score (lower is better)."""

    cell: int
    tilt: int
    score: float


def cell_name(row: int, col: int, rows: int, cols: int) -> str:
    """Human name of a grid cell ("top-left", "centre", ...) from where its centre falls in thirds
    of the image, so that any grid size reads naturally."""
    v = ("top", "", "bottom")[min(2, int(3 * (row + 0.5) / rows))]
    h = ("left", "", "right")[min(2, int(3 * (col + 0.5) / cols))]
    return "-".join(p for p in (v, h) if p) or "centre"


def tilt_angles(rvec: F64) -> tuple[float, float]:
    """(about vertical, about horizontal) tilt in degrees from the board plane's depth gradient:
    positive when the right (resp. bottom) side is farther from the camera."""
    n = cv2.Rodrigues(np.asarray(rvec, np.float64))[0][:, 2]
    nz = n[2] if abs(n[2]) > 1e-9 else 1e-9
    return math.degrees(math.atan(-n[0] / nz)), math.degrees(math.atan(-n[1] / nz))


def tilt_bin(angles: tuple[float, float], flat_deg: float = FLAT_DEG) -> int:
    """Index in TILT_BINS of a tilt (see tilt_angles)."""
    yaw, pitch = angles
    if max(abs(yaw), abs(pitch)) < flat_deg:
        return 0
    if abs(yaw) >= abs(pitch):
        return 1 if yaw > 0 else 2
    return 3 if pitch > 0 else 4


def _intrinsic_columns(model_params: Sequence[str]) -> list[int]:
    """Columns of cv2.projectPoints' Jacobian for fx fy cx cy and the model's distortion terms
    (layout: rvec 3, tvec 3, f 2, c 2, then the distortion vector)."""
    return [6, 7, 8, 9, *(10 + DIST_NAMES.index(p) for p in model_params)]


@dataclass(frozen=True)
class ViewPlanner:
    """The coverage grid of one camera and the next-view choice on it (module docstring).

    Stateless: the caller passes the current intrinsics (K, dist) and the kept views' poses."""

    board: BoardSpec
    image_size: tuple[int, int]
    grid: tuple[int, int]  # (cols, rows) of coverage cells
    lens: LensModel

    @property
    def n_cells(self) -> int:
        return self.grid[0] * self.grid[1]

    def cell_of_points(self, points: F64) -> int:
        """Grid cell of the centroid of image points."""
        cols, rows = self.grid
        w, h = self.image_size
        cx, cy = points.mean(axis=0)
        c = int(np.clip(cx / w * cols, 0, cols - 1))
        r = int(np.clip(cy / h * rows, 0, rows - 1))
        return r * cols + c

    def cell_name(self, cell: int) -> str:
        cols, rows = self.grid
        return cell_name(cell // cols, cell % cols, rows, cols)

    def depth(self, K: F64, tvecs: Sequence[F64]) -> float:
        """Distance for synthesised poses: the median of the kept views', or without views the
        distance at which the board spans ~40 % of the image width."""
        if tvecs:
            return float(np.median([float(np.linalg.norm(t)) for t in tvecs]))
        bc = self.board.inner_corners[0]
        return float(K[0, 0] * (bc + 1) * self.board.square_m / (0.4 * self.image_size[0]))

    def outline(self) -> F64:
        """The board's outer corners (one square of margin) in board coordinates."""
        bc, br = self.board.inner_corners
        sq = self.board.square_m
        return np.array(
            [[-sq, -sq, 0], [bc * sq, -sq, 0], [bc * sq, br * sq, 0], [-sq, br * sq, 0]], np.float64
        )

    def view_information(self, K: F64, dist: F64, obj: F64, rvec: F64, tvec: F64) -> tuple[F64, int]:
        """Information on the intrinsics of one view with its pose eliminated (Schur complement
        of J^T J), unscaled by the noise; and how many of its corners land inside the image."""
        cols = _intrinsic_columns(self.lens.params)
        proj, jac = cv2.projectPoints(obj.reshape(-1, 1, 3), rvec, tvec, K, dist)
        p = proj.reshape(-1, 2)
        w, h = self.image_size
        inside = (p[:, 0] >= 0) & (p[:, 0] <= w - 1) & (p[:, 1] >= 0) & (p[:, 1] <= h - 1)
        rows = np.repeat(inside, 2)
        J = np.asarray(jac, np.float64)[rows]
        Ji, Jp = J[:, cols], J[:, :6]
        A, B, C = Ji.T @ Ji, Ji.T @ Jp, Jp.T @ Jp
        try:
            S = A - B @ np.linalg.solve(C, B.T)
        except np.linalg.LinAlgError:
            S = np.zeros_like(A)
        return S, int(inside.sum())

    def prior(self, n: int) -> F64:
        """Weak prior (information) on [fx fy cx cy dist...]: sigma = image width for f, a quarter
        of it for c, 1 for distortion terms; only keeps the matrix invertible early on."""
        w = float(self.image_size[0])
        sig = np.array([w, w, w / 4, w / 4, *([1.0] * (n - 4))])
        return np.diag(1.0 / sig**2)

    def synthetic_pose(self, K: F64, dist: F64, cell: int, tilt: int, depth: float) -> tuple[F64, F64] | None:
        """Board pose whose corners' centroid lies in the cell, tilted as the bin says, with the
        whole board (margin included) in the image: aimed at the cell's centre, pushed inside the
        image, and moved farther (up to 2.4x `depth`) while pushing would leave the cell; None
        when no such pose is found."""
        cols, rows = self.grid
        w, h = self.image_size
        angle = math.radians(TILT_DEG)
        axis = {
            0: np.zeros(3),
            1: np.array([0.0, -angle, 0.0]),  # right edge away
            2: np.array([0.0, angle, 0.0]),
            3: np.array([angle, 0.0, 0.0]),  # bottom edge away
            4: np.array([-angle, 0.0, 0.0]),
        }[tilt]
        R = cv2.Rodrigues(axis)[0]
        rvec = cv2.Rodrigues(R)[0].ravel()
        bc, br = self.board.inner_corners
        sq = self.board.square_m
        mid = np.array([(bc - 1) * sq / 2, (br - 1) * sq / 2, 0.0])
        outline = self.outline()
        obj = self.board.object_points()
        Kinv = np.linalg.inv(K)
        size = np.array([w - 1.0, h - 1.0])
        for k in range(5):
            z = depth * 1.25**k
            target = np.array([((cell % cols) + 0.5) * w / cols, ((cell // cols) + 0.5) * h / rows])
            for _ in range(4):
                ray = Kinv @ np.array([target[0], target[1], 1.0])
                tvec = ray / ray[2] * z - R @ mid
                p = cv2.projectPoints(outline, rvec, tvec, K, dist)[0].reshape(-1, 2)
                lo, hi = p.min(axis=0), p.max(axis=0)
                if (hi - lo >= size).any():
                    break  # larger than the image at this depth
                shift = np.maximum(0, -lo) - np.maximum(0, hi - size)
                if not shift.any():
                    proj = cv2.projectPoints(obj, rvec, tvec, K, dist)[0]
                    if self.cell_of_points(np.asarray(proj, np.float64).reshape(-1, 2)) == cell:
                        return np.asarray(rvec, np.float64), np.asarray(tvec, np.float64)
                    break
                target = target + shift
        return None

    def best_information(
        self,
        K: F64,
        dist: F64,
        views: Sequence[tuple[F64, F64, F64]],
        rms: float | None,
        cov: NDArray[np.int64],
        unreachable: Collection[tuple[int, int]],
    ) -> Candidate | None:
        """The bin whose view would lower trace(Cov[fx, fy, cx, cy]) most (module docstring);
        `views` are the kept views' (object points, rvec, tvec); falls back to the emptiest bin."""
        n = 4 + len(self.lens.params)
        noise = rms if rms else _DEFAULT_NOISE_PX
        info = self.prior(n)
        for obj_v, rvec, tvec in views:
            info += self.view_information(K, dist, obj_v, rvec, tvec)[0] / noise**2
        depth = self.depth(K, [t for _, _, t in views])
        obj = self.board.object_points()
        best: Candidate | None = None
        for cell in range(self.n_cells):
            for tilt in range(len(TILT_BINS)):
                if (cell, tilt) in unreachable:
                    continue
                pose = self.synthetic_pose(K, dist, cell, tilt, depth)
                if pose is None:
                    continue
                S, n_in = self.view_information(K, dist, obj, *pose)
                if n_in < max(6, obj.shape[0] // 2):
                    continue
                try:
                    cov_c = np.linalg.inv(info + S / noise**2)
                except np.linalg.LinAlgError:
                    continue
                score = float(np.trace(cov_c[:4, :4]))
                # ties (e.g. before any view) go to the emptier bin, then to the first one
                if (
                    best is None
                    or score < best.score * (1 - 1e-9)
                    or (score <= best.score * (1 + 1e-9) and cov[cell, tilt] < cov[best.cell, best.tilt])
                ):
                    best = Candidate(cell, tilt, score)
        return best or self.emptiest(cov, unreachable)

    def emptiest(self, cov: NDArray[np.int64], unreachable: Collection[tuple[int, int]]) -> Candidate:
        """Heuristic: the bin with the fewest views; image corners and tilted views first (they
        constrain distortion and focal length most), then the rest in grid order."""
        cols, rows = self.grid
        corners = {0, cols - 1, (rows - 1) * cols, rows * cols - 1}
        bins = [(c, t) for c in range(self.n_cells) for t in range(len(TILT_BINS))]
        order = sorted(
            [b for b in bins if b not in unreachable] or bins,
            key=lambda ct: (cov[ct], ct[0] not in corners, ct[1] == 0, ct),
        )
        c, t = order[0]
        return Candidate(c, t, float(cov[c, t]))
