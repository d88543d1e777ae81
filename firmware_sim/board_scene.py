# ruff: noqa: N806  (R, K, t follow the notation of the calibration literature)
"""A calibration scene: a printed chessboard moving and tilting in front of the sim rig.

Why a separate scene: calibrating the rig (RGB intrinsics, e2calib-style event intrinsics, rig
extrinsics) needs a board whose pose is known exactly at every instant, seen by all five devices
at once, moving smoothly so the event sensors fire and tilting so focal length is observable.

How it plugs in: `BoardScene` is a `Scene` whose only "sprite" is the board. A sprite is drawn
through a texel -> image homography; `Scene` makes it from a similarity on the background plane,
`BoardScene` from the board's full 3-D pose (H = K [r1 r2 t] of the board in the camera, times
texel -> board metres). Everything the devices call (`view`, `render`, `render_intensity`,
`changing_roi(s)`, `substeps`, and the event kernel's `objects`, `sprite_stack`, `sprite_texels`,
`object_corners`, `object_homographies`) therefore works unchanged, including the fused numba
event kernel. The board is always composited over the background (it floats in front of it).

Board convention (the one of `calibration.boards` for chessboards): X along the columns, Y along
the rows, Z = 0 on the board, origin at the first inner corner; the top-left square is black. The
views are the ones of `Scene` (same K, R, t per device name and resolution), pinhole without lens
distortion. Select it in device specs with `scene=board` (see the sim device factories).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from drivers.registry import DeviceSpec
from firmware_sim.scene import (
    BG_TEXELS_PER_M,
    REF_HEIGHT,
    REF_WIDTH,
    Scene,
    SceneObject,
    View,
    _smooth_noise,
)
from firmware_sim.world import SimWorld
from rigd.core.errors import ConfigError

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]

#: Board texture resolution; 12 texels per square: about the resolution of a 640-wide view at
#: 2 m (measured: corner noise 0.06 px at 640x360, 0.03 px at 1280x720, 0.14 px at 320x180).
TEXELS_PER_SQUARE = 12
#: Board intensities (DN): black and white ink, not saturated, so events see both edges.
BLACK_DN, WHITE_DN = 30.0, 215.0
#: Mean distance of the board from the plane the views look at (towards the rig), metres.
BOARD_Z_M = -0.8


@dataclass(frozen=True, slots=True)
class BoardMotion:
    """Smooth motion: centre on a 3-D Lissajous path, tilt about X and Y and roll about Z.

    Amplitudes in metres and degrees, periods in seconds; phases come from the scene seed.
    The defaults keep the whole board inside all five views of the sim rig and its tilts within
    +-30 deg of facing the rig (so no view sees it at more than about 55 deg)."""

    amp_m: tuple[float, float, float] = (0.3, 0.16, 0.22)
    period_s: tuple[float, float, float] = (4.3, 3.1, 5.3)
    tilt_deg: tuple[float, float, float] = (28.0, 30.0, 12.0)
    tilt_period_s: tuple[float, float, float] = (2.9, 3.7, 6.1)


def _rot(axis: int, angle: F64) -> F64:
    """(..., 3, 3) rotations by `angle` (radians) about a coordinate axis."""
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros((*np.shape(angle), 3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    out[..., axis, axis] = 1.0
    out[..., i, i] = c
    out[..., j, j] = c
    out[..., i, j] = -s
    out[..., j, i] = s
    return out


def board_texture(cols: int, rows: int) -> tuple[F64, int, float]:
    """(gray intensity in DN, alpha) as an (S, S, 2) square texture, S, and the texel coordinate of
    the first inner corner (same in u and v).

    The board is (cols + 1) x (rows + 1) squares plus a half-square white margin; the texture is
    square because the event kernel assumes square sprites, with alpha 0 outside the board. Each
    texel is the average of 4x4 sub-samples of the exact pattern, so edges are antialiased and lie
    exactly at multiples of the square size on the board.
    """
    n = TEXELS_PER_SQUARE
    w_sq, h_sq = cols + 2, rows + 2  # squares, margins included
    side = max(w_sq, h_sq) * n
    ss = 4
    # Board coordinates in squares of sub-sample centres; the inner-corner origin is at texel
    # coordinate 1.5 squares (margin 0.5 + one outer square) minus half a texel (centre convention).
    sub = (np.arange(side * ss) + 0.5) / ss - 0.5  # texel coordinates of the sub-samples
    origin = 1.5 * n - 0.5
    q = (sub - origin) / n  # squares
    qx, qy = q[None, :], q[:, None]
    ix, iy = np.floor(qx), np.floor(qy)
    inside_sq = (ix >= -1) & (ix <= cols - 1) & (iy >= -1) & (iy <= rows - 1)
    black = inside_sq & (((ix + iy) % 2) == 0)
    board = (qx >= -1.5) & (qx < cols + 0.5) & (qy >= -1.5) & (qy < rows + 0.5)
    inten = np.where(black, BLACK_DN, WHITE_DN) * board
    inten_t = inten.reshape(side, ss, side, ss).mean(axis=(1, 3))
    alpha_t = board.astype(np.float64).reshape(side, ss, side, ss).mean(axis=(1, 3))
    # `inten` is already premultiplied (zero outside the board).
    return np.dstack([inten_t, alpha_t]), side, origin


class BoardScene(Scene):
    """The sim rig's views watching a moving chessboard; deterministic from its seed."""

    def __init__(
        self,
        seed: int = 0,
        cols: int = 9,
        rows: int = 6,
        square_m: float = 0.08,
        speed: float = 1.0,
        motion: BoardMotion | None = None,
    ) -> None:
        if cols < 2 or rows < 2 or square_m <= 0:
            raise ValueError(f"bad board {cols}x{rows} inner corners, square {square_m} m")
        super().__init__(seed=seed, n_objects=0, speed=speed)
        rng = np.random.default_rng([seed, 0xB0A4D])
        # A plain, low-contrast background: a textured one could hold chessboard-like corners.
        blobs = _smooth_noise(rng, (*self._bg_shape, 3), int(BG_TEXELS_PER_M / 2))
        self._bg_texture = np.clip(105.0 + 50.0 * blobs, 0, 255).astype(np.uint8)
        self.cols, self.rows, self.square_m = cols, rows, float(square_m)
        self.motion = motion or BoardMotion()
        self._phases = rng.uniform(0.0, 2 * math.pi, 6)
        tex, side, origin = board_texture(cols, rows)
        self._tpm = TEXELS_PER_SQUARE / self.square_m
        #: Texel (u, v, 1) -> board (X, Y, 1) in metres.
        self._board_from_texel = np.array(
            [[1 / self._tpm, 0, -origin / self._tpm], [0, 1 / self._tpm, -origin / self._tpm], [0, 0, 1]]
        )
        inten = tex.astype(np.float32)
        gray8 = np.dstack([np.rint(inten[..., 0]), np.rint(inten[..., 1] * 255)]).astype(np.uint8)
        rgb = np.repeat(gray8[..., :1], 3, axis=2)
        board = SceneObject(
            size_m=side / self._tpm,
            texels=side,
            amp=(0.0, 0.0),
            omega=(0.0, 0.0),
            phase=(0.0, 0.0),
            center=(0.0, 0.0),
            theta0=0.0,
            spin=0.0,
            rgba_premul=np.ascontiguousarray(np.dstack([rgb, gray8[..., 1:]])),
            gray_premul=np.ascontiguousarray(gray8),
            intensity_premul=np.ascontiguousarray(inten),
        )
        self.objects = [board]
        self.sprite_stack = np.ascontiguousarray(inten[None])
        self.sprite_texels = np.array([side], np.int64)
        log.debug("board scene %d: %dx%d board, %.3f m squares", seed, cols, rows, square_m)

    @property
    def board_spec(self) -> str:
        """The board as a calibration spec string (`chessboard:COLSxROWS:SQUARE`)."""
        return f"chessboard:{self.cols}x{self.rows}:{self.square_m:g}"

    def board_points(self) -> F64:
        """(N, 3) inner corners on the board in metres, row-major (the calibration order)."""
        g = np.mgrid[0 : self.cols, 0 : self.rows].T.reshape(-1, 2) * self.square_m
        return np.hstack([g, np.zeros((g.shape[0], 1))])

    # --- ground truth --------------------------------------------------------------------

    def board_pose(self, true_us: float | F64) -> tuple[F64, F64]:
        """(R, t) board -> world at true time(s): x_world = R @ X_board + t; shapes (..., 3, 3), (..., 3)."""
        ts = np.asarray(true_us, np.float64) * 1e-6 * self.speed
        m, ph = self.motion, self._phases
        centre = np.stack(
            [m.amp_m[i] * np.sin(2 * math.pi * ts / m.period_s[i] + ph[i]) for i in range(3)], axis=-1
        )
        centre[..., 2] += BOARD_Z_M
        ang = [
            np.radians(m.tilt_deg[i]) * np.sin(2 * math.pi * ts / m.tilt_period_s[i] + ph[3 + i])
            for i in range(3)
        ]
        R = _rot(1, ang[1]) @ _rot(0, ang[0]) @ _rot(2, ang[2])
        mid = np.array([(self.cols - 1) * self.square_m / 2, (self.rows - 1) * self.square_m / 2, 0.0])
        return R, centre - R @ mid

    def board_in_view(
        self, name: str, true_us: float | F64, width: int = REF_WIDTH, height: int = REF_HEIGHT
    ) -> tuple[F64, F64]:
        """(R, t) board -> camera of a device at true time(s): x_cam = R @ X_board + t."""
        v = self.view(name, width, height)
        Rwb, twb = self.board_pose(true_us)
        return v.R @ Rwb, np.einsum("ij,...j->...i", v.R, twb) + v.t

    def board_corners(
        self, name: str, true_us: float, width: int = REF_WIDTH, height: int = REF_HEIGHT
    ) -> F64:
        """(N, 2) exact image positions (pixel centres at integers) of the inner corners."""
        v = self.view(name, width, height)
        R, t = self.board_in_view(name, true_us, width, height)
        p = (v.K @ (R @ self.board_points().T + t[:, None])).T
        return p[:, :2] / p[:, 2:3]

    # --- what the devices and the event kernel call --------------------------------------

    def object_poses(self, true_us: float | F64) -> F64:
        """(..., 1, 3): board centre (x, y) in the world and its roll; kept for Scene's API."""
        R, t = self.board_pose(true_us)
        roll = np.arctan2(R[..., 1, 0], R[..., 0, 0])
        return np.stack([t[..., 0], t[..., 1], roll], axis=-1)[..., None, :]

    def object_homographies(self, view: View | str, true_us: float | F64) -> F64:
        """(..., 1, 3, 3): board texel -> image pixel at true time(s), from the 3-D board pose."""
        v = self._as_view(view)
        Rwb, twb = self.board_pose(true_us)
        Rcb = v.R @ Rwb
        tcb = np.einsum("ij,...j->...i", v.R, twb) + v.t
        H = np.stack([Rcb[..., :, 0], Rcb[..., :, 1], tcb], axis=-1)
        H = np.einsum("ij,...jk,kl->...il", v.K, H, self._board_from_texel)
        return H[..., None, :, :]


#: Values of the `scene` spec parameter.
SCENE_KINDS = ("sprites", "board")


def sim_scene(spec: DeviceSpec, world: SimWorld, seed: int) -> Scene:
    """The scene of a device's world, made on first use as the spec's `scene` parameter says.

    All devices of a world share one scene, so a spec asking for another kind than the world
    already holds is a ConfigError (mixed specs would silently watch different scenes)."""
    kind = spec.param("scene", "sprites")
    if kind not in SCENE_KINDS:
        raise ConfigError(f"device spec {spec.raw!r}: scene={kind!r} (use {' or '.join(SCENE_KINDS)})")
    make = (lambda: BoardScene(seed=seed)) if kind == "board" else (lambda: Scene(seed=seed))
    scene = world.resource("scene", make)
    if not isinstance(scene, Scene):
        raise ConfigError(f"device spec {spec.raw!r}: world {world.name!r} holds no Scene")
    if (kind == "board") != isinstance(scene, BoardScene):
        raise ConfigError(
            f"device spec {spec.raw!r}: scene={kind} but world {world.name!r} already holds a "
            f"{type(scene).__name__}; give every device of a world the same scene parameter"
        )
    return scene


def describe(scene: BoardScene, name: str, true_us: float, width: int, height: int) -> dict[str, object]:
    """Ground truth of one device at one instant, JSON-friendly (for benches and debugging)."""
    K, R, t = scene.view_camera(name, width, height)
    Rb, tb = scene.board_in_view(name, true_us, width, height)
    rvec = cv2.Rodrigues(Rb)[0].ravel()
    return {
        "K": K.tolist(),
        "R": R.tolist(),
        "t": t.tolist(),
        "board_rvec": rvec.tolist(),
        "board_t": tb.tolist(),
    }
