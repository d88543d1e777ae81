"""Dense optical flow between consecutive snapshots (OpenCV) and backward warping.

The paper converts events into optical flow in the event view and warps images along it to
supervise inserted timestamps (Eq. 7). Here the flow comes from OpenCV on consecutive intensity
snapshots (events -> e2i -> flow): DIS (Kroeger et al. 2016) with its three presets, the
speed/accuracy knob, and Farneback as a classical dense baseline. `flow(a, b)` is the forward
flow a -> b: a pixel at p in `a` is at p + F(p) in `b`. `backward_warp(b, flow)` samples b at
p + F(p), which reproduces `a` wherever the pixel is visible in both.

Inputs may be any float or integer images; they are mapped to uint8 on a common scale (the flow
methods are 8-bit), so log-intensity snapshots work directly.
"""

from __future__ import annotations

import logging
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

F32 = NDArray[np.float32]
Preset = Literal["dis_ultrafast", "dis_fast", "dis_medium", "farneback"]
PRESETS: tuple[Preset, ...] = ("dis_ultrafast", "dis_fast", "dis_medium", "farneback")
_DIS = {
    "dis_ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "dis_fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "dis_medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


def to_u8_pair(a: NDArray[np.generic], b: NDArray[np.generic]) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """Both images on one 8-bit scale (min..max over the pair), so brightness stays comparable."""
    fa = np.asarray(a, np.float32)
    fb = np.asarray(b, np.float32)
    if fa.shape != fb.shape or fa.ndim != 2:
        raise ValueError(f"flow needs two gray images of one shape, got {fa.shape} and {fb.shape}")
    lo = min(float(fa.min()), float(fb.min()))
    hi = max(float(fa.max()), float(fb.max()))
    k = 255.0 / (hi - lo) if hi > lo else 0.0
    ua = np.clip((fa - lo) * k + 0.5, 0, 255).astype(np.uint8)
    ub = np.clip((fb - lo) * k + 0.5, 0, 255).astype(np.uint8)
    return ua, ub


class FlowEstimator:
    """One reusable flow engine (DIS objects are stateful and cheap to reuse across pairs)."""

    def __init__(self, preset: Preset = "dis_medium") -> None:
        if preset not in PRESETS:
            raise ValueError(f"unknown flow preset {preset!r}; choose one of {PRESETS}")
        self.preset: Preset = preset
        self._dis = cv2.DISOpticalFlow.create(_DIS[preset]) if preset in _DIS else None

    def __call__(self, a: NDArray[np.generic], b: NDArray[np.generic]) -> F32:
        """(H, W, 2) forward flow a -> b in pixels (dx, dy)."""
        ua, ub = to_u8_pair(a, b)
        init = np.zeros((*ua.shape, 2), np.float32)  # not used as initial flow (flags off)
        if self._dis is not None:
            out = self._dis.calc(ua, ub, init)
        else:
            out = cv2.calcOpticalFlowFarneback(ua, ub, init, 0.5, 4, 21, 5, 7, 1.5, 0)
        return np.asarray(out, np.float32)


def flow(a: NDArray[np.generic], b: NDArray[np.generic], preset: Preset = "dis_medium") -> F32:
    """(H, W, 2) forward flow a -> b with a fresh estimator."""
    return FlowEstimator(preset)(a, b)


def backward_warp(
    img: NDArray[np.generic], flow_field: NDArray[np.generic], border: str = "replicate"
) -> F32:
    """out(p) = img(p + flow(p)) with bilinear sampling: brings `b` back onto `a`'s grid."""
    im = np.asarray(img, np.float32)
    f = np.asarray(flow_field, np.float32)
    h, w = im.shape[:2]
    if f.shape != (h, w, 2):
        raise ValueError(f"flow shape {f.shape} does not match image {im.shape}")
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    mode = cv2.BORDER_REPLICATE if border == "replicate" else cv2.BORDER_CONSTANT
    return np.asarray(
        cv2.remap(im, gx + f[..., 0], gy + f[..., 1], cv2.INTER_LINEAR, borderMode=mode), np.float32
    )


def endpoint_error(
    pred: NDArray[np.generic], gt: NDArray[np.generic], mask: NDArray[np.bool_] | None = None
) -> float:
    """Mean end-point error |pred - gt| in pixels (over `mask` when given)."""
    d = np.linalg.norm(np.asarray(pred, np.float64) - np.asarray(gt, np.float64), axis=-1)
    if mask is not None:
        m = np.asarray(mask, bool)
        return float(d[m].mean()) if m.any() else float("nan")
    return float(d.mean())
