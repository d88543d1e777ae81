"""A planar scene with exact ground truth, rendered fast enough for real-time devices.

The world is the plane z = 0 (metres, X right, Y down): a textured background plus a few
textured sprites (alpha-masked objects lying on the plane) that translate along smooth
Lissajous paths and rotate. Each view (RGB camera or event sensor) is a pinhole camera
(K, R, t) looking at the plane, so plane -> image is the homography H = K [r1 r2 t] and
sprite texel -> image is H @ S(t), with S(t) the sprite's similarity on the plane.

Speed comes from never re-rendering what does not change: each view's background is
warped once, and a render only warps the sprites into their image bounding boxes.
The event sensors additionally restrict themselves to `changing_rois`.

Intensities are in digital numbers 0..255. The log-intensity seen by event pixels is
`lin_log`: log(I + LOG_EPS) above LIN_LOG_KNEE, continued by its tangent line below, so
dark pixels do not turn quantisation noise into event storms (the v2e convention).
"""

from __future__ import annotations

import logging
import math
import threading
import zlib
from dataclasses import dataclass, field

import cv2
import numpy as np
from numba import njit
from numpy.typing import NDArray

from rigd.core.pixels import mosaic_rggb

log = logging.getLogger(__name__)

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]
Box = tuple[int, int, int, int]
"""(x0, y0, x1, y1), half-open pixel box."""

#: Offset added to the intensity (DN) before the log; keeps log finite at I = 0.
LOG_EPS = 1.0
#: Below this intensity (DN, after adding LOG_EPS) the log is replaced by its tangent line.
LIN_LOG_KNEE = 20.0

#: Reference resolution of the intrinsics; other resolutions scale K with the width.
REF_WIDTH, REF_HEIGHT, REF_FOCAL = 1280, 720, 1000.0
#: Sprite texture resolution, texels per metre (about the image resolution at 3 m).
TEXELS_PER_M = 320.0
#: Background texture resolution; its content is coarse, so half the sprites' is enough.
BG_TEXELS_PER_M = 160.0
#: Distance of every view from the plane centre, metres.
VIEW_DISTANCE_M = 3.0
#: The rig's arc: (yaw, elevation) in degrees; cameras and event sensors interleave.
RIG_POSES_DEG: dict[str, tuple[float, float]] = {
    "cam0": (-24.0, 2.0),
    "ev0": (-12.0, -3.0),
    "cam1": (0.0, 2.0),
    "ev1": (12.0, -3.0),
    "cam2": (24.0, 2.0),
}
_PLANE_HALF_EXTENT_M = (5.5, 3.2)
_BG_GRAY = 128


@njit(nogil=True, cache=True)
def _lin_log_kernel(inten: F32, out: F32, eps: float, knee: float) -> None:  # pragma: no cover - numba
    log_knee = math.log(knee)
    h, w = inten.shape
    for i in range(h):
        for j in range(w):
            v = inten[i, j] + eps
            if v >= knee:
                out[i, j] = math.log(v)
            else:
                out[i, j] = log_knee + (v - knee) / knee


@njit(nogil=True, cache=True)
def _blend_premul_kernel(dst: U8, warped: U8) -> None:  # pragma: no cover - numba
    """dst = dst * (1 - a) + premultiplied colour, rounded in integers, in place: warped is
    (h, w, c + 1) with alpha last, dst (h, w, c). Compiled and nogil so the cameras render
    in parallel with each other and the event sensors."""
    h, w, c = dst.shape
    for i in range(h):
        for j in range(w):
            inv = 255 - np.uint16(warped[i, j, c])
            for k in range(c):
                v = (np.uint16(dst[i, j, k]) * inv + 127) // 255 + np.uint16(warped[i, j, k])
                dst[i, j, k] = v if v < 255 else 255


@njit(nogil=True, cache=True)
def _blend_premul_bayer_kernel(  # pragma: no cover - numba
    dst: U8, warped: U8, x_odd: int, y_odd: int
) -> None:
    """`_blend_premul_kernel` into an RGGB mosaic: each pixel blends the one channel its
    filter passes (R at even row and column, B at odd, G elsewhere; parities of dst's origin
    given), which is exactly the mosaic of the RGB blend, at a third of the work."""
    h, w = dst.shape
    for i in range(h):
        for j in range(w):
            c = ((i + y_odd) & 1) + ((j + x_odd) & 1)
            inv = 255 - np.uint16(warped[i, j, 3])
            v = (np.uint16(dst[i, j]) * inv + 127) // 255 + np.uint16(warped[i, j, c])
            dst[i, j] = v if v < 255 else 255


#: Table of lin_log on [0, 256] in steps of 1/LOG_LUT_SCALE, for kernels (linear interpolation
#: between entries is within 2e-6 of the exact value).
LOG_LUT_SCALE = 16.0


def log_lut() -> F32:
    """lin_log sampled every 1/LOG_LUT_SCALE DN on [0, 256 + 1/LOG_LUT_SCALE]."""
    xs = (np.arange(int(256 * LOG_LUT_SCALE) + 2, dtype=np.float64) / LOG_LUT_SCALE).astype(np.float32)
    return lin_log(xs[None, :])[0]


def lin_log(intensity: F32) -> F32:
    """Log intensity of a 2-D float32 image (DN), linear near zero; see module docstring."""
    inten = np.ascontiguousarray(intensity, dtype=np.float32)
    out = np.empty_like(inten)
    _lin_log_kernel(inten, out, LOG_EPS, LIN_LOG_KNEE)
    return out


def look_at_pose(center: F64, target: F64 | None = None) -> tuple[F64, F64]:
    """(R, t) of a camera at `center` looking at `target`, image y along world +Y (down)."""
    tgt = np.zeros(3) if target is None else np.asarray(target, np.float64)
    c = np.asarray(center, np.float64)
    f = tgt - c
    f /= np.linalg.norm(f)
    x = np.cross(np.array([0.0, 1.0, 0.0]), f)
    x /= np.linalg.norm(x)
    y = np.cross(f, x)
    r = np.stack([x, y, f])
    return r, -r @ c


def _arc_center(yaw_deg: float, elev_deg: float, dist: float) -> F64:
    yaw, el = math.radians(yaw_deg), math.radians(elev_deg)
    return np.array(
        [dist * math.sin(yaw) * math.cos(el), -dist * math.sin(el), -dist * math.cos(yaw) * math.cos(el)]
    )


def pose_angles(name: str) -> tuple[float, float]:
    """(yaw, elevation) in degrees: the rig's for known names, hashed from the name otherwise."""
    if name in RIG_POSES_DEG:
        return RIG_POSES_DEG[name]
    h = zlib.crc32(name.encode())
    return -30.0 + (h % 6001) / 100.0, ((h >> 13) % 1001) / 100.0 - 5.0


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, ...], cell: int) -> F32:
    """Band-limited noise in [0, 1]: random values on a coarse grid, cubic upsampled."""
    h, w = shape[:2]
    coarse_shape = (max(2, h // cell + 2), max(2, w // cell + 2), *shape[2:])
    coarse = rng.random(coarse_shape).astype(np.float32)
    big = cv2.resize(coarse, (w + 2 * cell, h + 2 * cell), interpolation=cv2.INTER_CUBIC)
    out = big[cell : cell + h, cell : cell + w]
    lo, hi = float(out.min()), float(out.max())
    return ((out - lo) / max(hi - lo, 1e-6)).astype(np.float32)


def _background_texture(rng: np.random.Generator, shape: tuple[int, int]) -> U8:
    """Blobs of colour over a faint checker: real spatial content, moderate contrast."""
    h, w = shape
    cell = int(BG_TEXELS_PER_M / 4)  # 25 cm checker squares
    check = ((np.arange(h)[:, None] // cell + np.arange(w)[None, :] // cell) % 2).astype(np.float32)
    blobs = _smooth_noise(rng, (h, w, 3), 24)
    rgb = 70.0 + 110.0 * blobs + 25.0 * check[..., None]
    return np.clip(rgb, 0, 255).astype(np.uint8)


def _sprite_texture(rng: np.random.Generator, size: int, kind: int) -> tuple[U8, F32]:
    """(RGB texture, alpha in [0, 1]) of one object; kind picks the pattern and the shape."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    c = (size - 1) / 2.0
    u, v = (xx - c) / c, (yy - c) / c
    # A dark and a bright colour, so the pattern has contrast in gray too.
    base = rng.uniform(25, 100, 3).astype(np.float32)
    accent = rng.uniform(150, 240, 3).astype(np.float32)
    if rng.random() < 0.5:
        base, accent = accent, base
    if kind % 3 == 0:  # stripes
        ang = rng.uniform(0, math.pi)
        s = np.sin((u * math.cos(ang) + v * math.sin(ang)) * rng.uniform(4, 7) * math.pi)
        mix = (s > 0).astype(np.float32)
    elif kind % 3 == 1:  # checker
        n = int(rng.integers(4, 7))
        mix = ((np.floor((u + 1) * n / 2) + np.floor((v + 1) * n / 2)) % 2).astype(np.float32)
    else:  # blobs
        mix = (_smooth_noise(rng, (size, size), max(6, size // 10)) > 0.5).astype(np.float32)
    mix = cv2.GaussianBlur(mix, (0, 0), 0.8)
    rgb = base[None, None, :] * (1 - mix[..., None]) + accent[None, None, :] * mix[..., None]
    # Shape: disk, rounded square or ellipse; a 1.5-texel soft edge antialiases it.
    if kind % 3 == 0:
        dist = np.sqrt(u * u + v * v) - 0.97
    elif kind % 3 == 1:
        q = np.maximum(np.abs(u), np.abs(v))
        dist = np.where(
            q > 0.7,
            np.sqrt(np.maximum(np.abs(u) - 0.7, 0) ** 2 + np.maximum(np.abs(v) - 0.7, 0) ** 2) - 0.27,
            q - 0.97,
        )
    else:
        dist = np.sqrt((u / 0.97) ** 2 + (v / 0.7) ** 2) - 1.0
    alpha = np.clip(0.5 - dist * c / 1.5, 0.0, 1.0).astype(np.float32)
    return np.clip(rgb, 0, 255).astype(np.uint8), alpha


@dataclass(frozen=True, slots=True)
class SceneObject:
    """One sprite and its motion: centre (x, y) on Lissajous paths, angle linear + wobble."""

    size_m: float
    texels: int
    amp: tuple[float, float]
    omega: tuple[float, float]
    phase: tuple[float, float]
    center: tuple[float, float]
    theta0: float
    spin: float
    rgba_premul: U8 = field(repr=False)
    gray_premul: U8 = field(repr=False)
    intensity_premul: F32 = field(repr=False)


@dataclass(slots=True)
class View:
    """One device's ground-truth camera at one resolution, with its pre-warped background."""

    name: str
    width: int
    height: int
    K: F64
    R: F64
    t: F64
    H: F64
    """Plane (metres) -> image (pixels)."""
    bg_rgb: U8 = field(repr=False)
    bg_gray: U8 = field(repr=False)
    bg_intensity: F32 = field(repr=False)
    bg_log: F32 = field(repr=False)


class Scene:
    """The shared scene of one simulated world; deterministic from its seed, thread-safe."""

    def __init__(self, seed: int = 0, n_objects: int = 3, speed: float = 1.0) -> None:
        if n_objects < 0:
            raise ValueError(f"n_objects must be >= 0, got {n_objects}")
        self.seed = seed
        self.speed = float(speed)
        rng = np.random.default_rng([seed, 0x5CE7E])
        hx, hy = _PLANE_HALF_EXTENT_M
        self._bg_shape = (int(2 * hy * BG_TEXELS_PER_M), int(2 * hx * BG_TEXELS_PER_M))
        self._bg_texture = _background_texture(rng, self._bg_shape)
        self._bg_from_plane = np.array(
            [[1 / BG_TEXELS_PER_M, 0, -hx], [0, 1 / BG_TEXELS_PER_M, -hy], [0, 0, 1]], np.float64
        )
        self.objects: list[SceneObject] = [self._make_object(rng, i) for i in range(n_objects)]
        smax = max((o.texels for o in self.objects), default=1)
        #: All sprites' premultiplied intensity + alpha, zero-padded to one size, for kernels.
        self.sprite_stack = np.zeros((max(len(self.objects), 1), smax, smax, 2), np.float32)
        for i, o in enumerate(self.objects):
            self.sprite_stack[i, : o.texels, : o.texels] = o.intensity_premul
        self.sprite_texels = np.array([o.texels for o in self.objects] or [1], np.int64)
        self._views: dict[tuple[str, int, int], View] = {}
        self._bg_bayer: dict[tuple[str, int, int], U8] = {}
        self._lock = threading.Lock()

    @staticmethod
    def _make_object(rng: np.random.Generator, i: int) -> SceneObject:
        size_m = float(rng.uniform(0.26, 0.36))
        texels = round(size_m * TEXELS_PER_M)
        rgb, alpha = _sprite_texture(rng, texels, i)
        amp = (float(rng.uniform(0.6, 1.1)), float(rng.uniform(0.25, 0.45)))
        # Peak speed 0.7-1.4 m/s along x (about 230-470 px/s in the image at 3 m).
        peak = float(rng.uniform(0.7, 1.4))
        wx = peak / amp[0]
        wy = wx * float(rng.uniform(0.6, 1.4))
        spin = float(rng.uniform(0.3, 1.0)) * float(rng.choice([-1.0, 1.0]))
        prem = rgb.astype(np.float32) * alpha[..., None]
        a8 = np.rint(alpha * 255).astype(np.uint8)
        rgba = np.dstack([np.rint(prem).astype(np.uint8), a8])
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
        gray_prem = np.dstack([np.rint(gray * alpha).astype(np.uint8), a8])
        inten = np.dstack([gray * alpha, alpha]).astype(np.float32)
        return SceneObject(
            size_m=size_m,
            texels=texels,
            amp=amp,
            omega=(wx, wy),
            phase=(float(rng.uniform(0, 2 * math.pi)), float(rng.uniform(0, 2 * math.pi))),
            center=(float(rng.uniform(-0.5, 0.5)), float(rng.uniform(-0.3, 0.3))),
            theta0=float(rng.uniform(0, 2 * math.pi)),
            spin=spin,
            rgba_premul=np.ascontiguousarray(rgba),
            gray_premul=np.ascontiguousarray(gray_prem),
            intensity_premul=np.ascontiguousarray(inten),
        )

    # --- geometry -------------------------------------------------------------------------

    def view(self, name: str, width: int = REF_WIDTH, height: int = REF_HEIGHT) -> View:
        """The view of a device at a resolution, made (and its background warped) on first use."""
        key = (name, int(width), int(height))
        with self._lock:
            v = self._views.get(key)
            if v is None:
                v = self._views[key] = self._make_view(*key)
            return v

    def _make_view(self, name: str, width: int, height: int) -> View:
        if width <= 0 or height <= 0:
            raise ValueError(f"view {name}: bad resolution {width}x{height}")
        f = REF_FOCAL * width / REF_WIDTH
        k = np.array([[f, 0, width / 2.0], [0, f, height / 2.0], [0, 0, 1]], np.float64)
        yaw, elev = pose_angles(name)
        r, t = look_at_pose(_arc_center(yaw, elev, VIEW_DISTANCE_M))
        h = k @ np.column_stack([r[:, 0], r[:, 1], t])
        h_bg = h @ self._bg_from_plane
        size = (width, height)
        warped = cv2.warpPerspective(
            self._bg_texture,
            h_bg,
            size,
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=(_BG_GRAY, _BG_GRAY, _BG_GRAY),
        )
        bg: U8 = np.ascontiguousarray(warped, dtype=np.uint8)
        gray = np.ascontiguousarray(cv2.cvtColor(bg, cv2.COLOR_RGB2GRAY), dtype=np.uint8)
        log.debug("scene %d: made view %s %dx%d", self.seed, name, width, height)
        inten = gray.astype(np.float32)
        return View(name, width, height, k, r, t, h, bg, gray, inten, lin_log(inten))

    def _as_view(self, view: View | str) -> View:
        return self.view(view) if isinstance(view, str) else view

    def view_camera(
        self, name: str, width: int = REF_WIDTH, height: int = REF_HEIGHT
    ) -> tuple[F64, F64, F64]:
        """Ground-truth (K, R, t) of a device: x_cam = R @ x_world + t, pixels = K @ x_cam."""
        v = self.view(name, width, height)
        return v.K.copy(), v.R.copy(), v.t.copy()

    def plane_homography(self, name: str, width: int = REF_WIDTH, height: int = REF_HEIGHT) -> F64:
        """Plane (X, Y metres, z = 0) -> image pixels: K [r1 r2 t]."""
        return self.view(name, width, height).H.copy()

    def object_poses(self, true_us: float | F64) -> F64:
        """(..., n_objects, 3) of (x m, y m, theta rad) at true time(s) in microseconds."""
        ts = np.asarray(true_us, np.float64) * 1e-6 * self.speed
        out = np.empty((*ts.shape, len(self.objects), 3), np.float64)
        for i, o in enumerate(self.objects):
            out[..., i, 0] = o.center[0] + o.amp[0] * np.sin(o.omega[0] * ts + o.phase[0])
            out[..., i, 1] = o.center[1] + o.amp[1] * np.sin(o.omega[1] * ts + o.phase[1])
            out[..., i, 2] = o.theta0 + o.spin * ts + 0.3 * np.sin(0.7 * o.omega[0] * ts)
        return out

    def _sprite_to_plane(self, poses: F64) -> F64:
        """(..., n, 3, 3) similarity: sprite texel (u, v) -> plane metres."""
        n = len(self.objects)
        m = np.zeros((*poses.shape[:-1], 3, 3), np.float64)
        scale = np.array([o.size_m / o.texels for o in self.objects])
        half = np.array([(o.texels - 1) / 2.0 for o in self.objects])
        c, s = np.cos(poses[..., 2]), np.sin(poses[..., 2])
        sc, ss = scale * c, scale * s
        assert poses.shape[-2] == n
        m[..., 0, 0], m[..., 0, 1] = sc, -ss
        m[..., 1, 0], m[..., 1, 1] = ss, sc
        m[..., 0, 2] = poses[..., 0] - (sc - ss) * half
        m[..., 1, 2] = poses[..., 1] - (ss + sc) * half
        m[..., 2, 2] = 1.0
        return m

    def object_homographies(self, view: View | str, true_us: float | F64) -> F64:
        """(..., n_objects, 3, 3): sprite texel -> image pixel of each object at true time(s)."""
        v = self._as_view(view)
        return np.einsum("ij,...jk->...ik", v.H, self._sprite_to_plane(self.object_poses(true_us)))

    def object_corners(self, view: View | str, true_us: F64) -> F64:
        """(..., n, 4, 2) image positions of each sprite's texture corners (the quad it covers)."""
        return self.corners_of(self.object_homographies(view, true_us))

    def corners_of(self, hs: F64) -> F64:
        """(..., n, 4, 2) sprite corners in the image under texel -> image homographies hs."""
        sz = np.array([o.texels - 1 for o in self.objects], np.float64)
        corners = np.zeros((len(self.objects), 4, 3))
        corners[:, :, 2] = 1.0
        corners[:, 1, 0] = corners[:, 2, 0] = sz
        corners[:, 2, 1] = corners[:, 3, 1] = sz
        p = np.einsum("...nij,nkj->...nki", hs, corners)
        return p[..., :2] / p[..., 2:3]

    def _object_boxes(self, v: View, true_us: F64) -> NDArray[np.int64]:
        """(T, n, 4) integer image boxes of each object at each time, 2 px margin, unclipped."""
        xy = self.object_corners(v, true_us)
        lo = np.floor(xy.min(axis=-2)) - 2
        hi = np.ceil(xy.max(axis=-2)) + 3
        return np.concatenate([lo, hi], axis=-1).astype(np.int64)

    def _clip(self, v: View, b: NDArray[np.int64] | Box) -> Box | None:
        x0, y0 = max(int(b[0]), 0), max(int(b[1]), 0)
        x1, y1 = min(int(b[2]), v.width), min(int(b[3]), v.height)
        return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None

    def substeps(self, view: View | str, t0_us: float, t1_us: float, max_step_px: float = 1.5) -> int:
        """Sub-steps needed in [t0, t1] so no sprite corner moves more than max_step_px per step."""
        return len(self.step_homographies(view, t0_us, t1_us, max_step_px)[0]) - 1

    def step_homographies(
        self,
        view: View | str,
        t0_us: float,
        t1_us: float,
        max_step_px: float = 1.5,
        max_step_us: float = math.inf,
    ) -> tuple[F64, F64]:
        """Sub-step times over [t0, t1] (n + 1, so no sprite corner moves more than
        max_step_px, and no step lasts more than max_step_us) and the sprites' homographies at
        them ((n + 1, n_obj, 3, 3)).

        The probe that sizes the steps already evaluates the poses where the usual steps fall
        (an event sensor's slice in one or two steps), so a slice costs one pass over the
        scene's motion, not three.
        """
        v = self._as_view(view)
        if not self.objects or self.speed == 0.0 or t1_us <= t0_us:
            times = np.array([t0_us, t1_us], np.float64)
            return times, self.object_homographies(v, times)
        # Corner paths are smooth; sampling 4 points per coarse step bounds the path length.
        n_probe = max(2, min(64, int((t1_us - t0_us) / 2000.0) + 2))
        ts = np.linspace(t0_us, t1_us, n_probe)
        hs = self.object_homographies(v, ts)
        xy = self.corners_of(hs)
        path = np.linalg.norm(np.diff(xy, axis=0), axis=-1).sum(axis=0)  # (n, 4) px travelled
        n_sub = max(1, math.ceil(float(path.max()) / max_step_px), math.ceil((t1_us - t0_us) / max_step_us))
        times = np.linspace(t0_us, t1_us, n_sub + 1)
        if (n_probe - 1) % n_sub == 0:  # the steps fall on probes (1 or 2 steps a slice, usually)
            return times, hs[:: (n_probe - 1) // n_sub]
        return times, self.object_homographies(v, times)

    def changing_rois(self, view: View | str, times_us: F64) -> list[Box]:
        """Disjoint boxes covering every pixel that may change between the given times."""
        v = self._as_view(view)
        if not self.objects or len(times_us) == 0:
            return []
        boxes = self._object_boxes(v, np.asarray(times_us, np.float64))  # (T, n, 4)
        per_obj = [
            (int(b[:, 0].min()), int(b[:, 1].min()), int(b[:, 2].max()), int(b[:, 3].max()))
            for b in np.moveaxis(boxes, 1, 0)
        ]
        if self.speed == 0.0:
            return []
        clipped = [c for c in (self._clip(v, b) for b in per_obj) if c is not None]
        return _merge_boxes(clipped)

    def changing_roi(self, view: View | str, t0_us: float, t1_us: float) -> Box | None:
        """Union of sprite boxes over [t0, t1], clipped to the image; None when nothing moves."""
        v = self._as_view(view)
        n = self.substeps(v, t0_us, t1_us)
        rois = self.changing_rois(v, np.linspace(t0_us, t1_us, n + 1))
        if not rois:
            return None
        arr = np.array(rois)
        return (int(arr[:, 0].min()), int(arr[:, 1].min()), int(arr[:, 2].max()), int(arr[:, 3].max()))

    # --- rendering ------------------------------------------------------------------------

    def _sprites_in(self, v: View, true_us: float, box: Box) -> list[tuple[int, Box, F64]]:
        """(object index, clipped box inside `box`, homography into that box) of visible sprites."""
        hs = self.object_homographies(v, true_us)
        boxes = self._object_boxes(v, np.array([true_us]))[0]
        out = []
        for i, b in enumerate(boxes):
            x0, y0 = max(int(b[0]), box[0]), max(int(b[1]), box[1])
            x1, y1 = min(int(b[2]), box[2]), min(int(b[3]), box[3])
            if x1 > x0 and y1 > y0:
                shift = np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1]], np.float64)
                out.append((i, (x0, y0, x1, y1), shift @ hs[i]))
        return out

    def _full_box(self, v: View, roi: Box | None) -> Box:
        if roi is None:
            return (0, 0, v.width, v.height)
        c = self._clip(v, roi)
        if c is None or tuple(roi) != c:
            raise ValueError(f"roi {roi} is not inside the {v.width}x{v.height} view {v.name}")
        return c

    def _warped_sprites(self, v: View, true_us: float, box: Box, gray: bool) -> list[tuple[Box, U8]]:
        """Each visible sprite warped into its own box inside `box` (box-relative), in drawing
        order: premultiplied colour with alpha last."""
        out = []
        for i, (x0, y0, x1, y1), h in self._sprites_in(v, true_us, box):
            o = self.objects[i]
            src = o.gray_premul if gray else o.rgba_premul
            warped: U8 = np.asarray(cv2.warpPerspective(src, h, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR))
            out.append(((x0 - box[0], y0 - box[1], x1 - box[0], y1 - box[1]), warped))
        return out

    def render(self, view: View | str, true_us: float, roi: Box | None = None, gray: bool = False) -> U8:
        """uint8 image of the view (H, W, 3) RGB or (H, W) gray, or of `roi` only."""
        v = self._as_view(view)
        box = self._full_box(v, roi)
        bg = v.bg_gray if gray else v.bg_rgb
        out = bg[box[1] : box[3], box[0] : box[2]].copy()
        for (x0, y0, x1, y1), warped in self._warped_sprites(v, true_us, box, gray):
            dst = out[y0:y1, x0:x1]
            _blend_premul_kernel(dst[..., None] if gray else dst, warped)
        return out

    def render_bayer(self, view: View | str, true_us: float) -> U8:
        """The RGGB mosaic (H, W) a Bayer sensor records: exactly `mosaic_rggb` of `render`'s
        RGB image, made from the background's mosaic (once per view) and only the sprites'
        pixels, so a frame costs a third of the copying and blending of an RGB one."""
        v = self._as_view(view)
        key = (v.name, v.width, v.height)
        with self._lock:
            bg = self._bg_bayer.get(key)
            if bg is None:
                bg = self._bg_bayer[key] = mosaic_rggb(v.bg_rgb)
        out = bg.copy()
        for (x0, y0, x1, y1), warped in self._warped_sprites(v, true_us, (0, 0, v.width, v.height), False):
            _blend_premul_bayer_kernel(out[y0:y1, x0:x1], warped, x0 & 1, y0 & 1)
        return out

    def render_intensity(self, view: View | str, true_us: float, roi: Box | None = None) -> F32:
        """float32 gray intensity (DN, 0..255) of the view or of `roi`, for event pixels."""
        v = self._as_view(view)
        box = self._full_box(v, roi)
        out = v.bg_intensity[box[1] : box[3], box[0] : box[2]].copy()
        for i, (x0, y0, x1, y1), h in self._sprites_in(v, true_us, box):
            warped = cv2.warpPerspective(
                self.objects[i].intensity_premul, h, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR
            )
            dst = out[y0 - box[1] : y1 - box[1], x0 - box[0] : x1 - box[0]]
            dst *= 1.0 - warped[..., 1]
            dst += warped[..., 0]
        return out


def _merge_boxes(boxes: list[Box]) -> list[Box]:
    """Merge overlapping boxes into their unions until all are disjoint."""
    out = list(boxes)
    merged = True
    while merged:
        merged = False
        for i in range(len(out)):
            for j in range(i + 1, len(out)):
                a, b = out[i], out[j]
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    out[i] = (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))
                    del out[j]
                    merged = True
                    break
            if merged:
                break
    return out
