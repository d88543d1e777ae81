"""Image quality metrics of the paper's tables: PSNR, SSIM, and PSNR-ROI over the motion region.

PSNR-ROI is PSNR restricted to a region of interest (the motion region: where the ground truth
changes, or a mask the caller gives), because a mostly static image otherwise makes any method
look good: the paper reports it for exactly that reason. SSIM is the Wang et al. 2004 index with
a Gaussian window (sigma 1.5, K1 0.01, K2 0.03) as in EVREAL / scikit-image `gaussian_weights`.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: Cap on PSNR for identical images (dB), so tables and means stay finite.
PSNR_MAX_DB = 100.0


def psnr(pred: NDArray[np.generic], target: NDArray[np.generic], data_range: float = 255.0) -> float:
    """Peak signal-to-noise ratio in dB (capped at PSNR_MAX_DB)."""
    a = np.asarray(pred, np.float64)
    b = np.asarray(target, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"shapes differ: {a.shape} vs {b.shape}")
    if a.size == 0:
        raise ValueError("empty images")
    mse = float(np.mean((a - b) ** 2))
    if mse <= 0:
        return PSNR_MAX_DB
    return float(min(10.0 * np.log10(data_range**2 / mse), PSNR_MAX_DB))


def psnr_roi(
    pred: NDArray[np.generic], target: NDArray[np.generic], roi: NDArray[np.bool_], data_range: float = 255.0
) -> float:
    """PSNR over the pixels where `roi` is True (NaN when the ROI is empty)."""
    mask = np.asarray(roi, bool)
    if mask.shape != np.shape(target)[: mask.ndim]:
        raise ValueError(f"roi shape {mask.shape} does not match image {np.shape(target)}")
    if not mask.any():
        return float("nan")
    return psnr(np.asarray(pred)[mask], np.asarray(target)[mask], data_range)


def motion_roi(frames: NDArray[np.generic], threshold: float = 4.0, dilate_px: int = 5) -> NDArray[np.bool_]:
    """Motion region of a (N, H, W) ground-truth sequence: pixels whose value range over the
    sequence exceeds `threshold`, dilated so that edges and their surroundings are included."""
    arr = np.asarray(frames, np.float32)
    rng = arr.max(axis=0) - arr.min(axis=0)
    mask = (rng > threshold).astype(np.uint8)
    if dilate_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilate_px + 1, 2 * dilate_px + 1))
        mask = cv2.dilate(mask, k)
    return mask.astype(bool)


def _gauss(img: F64, sigma: float) -> F64:
    return np.asarray(cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_REFLECT), np.float64)


def ssim_components(
    a: NDArray[np.generic], b: NDArray[np.generic], data_range: float = 255.0, sigma: float = 1.5
) -> tuple[F64, F64]:
    """Per-pixel (luminance term, contrast-structure term) of SSIM; SSIM = their product."""
    x = np.asarray(a, np.float64)
    y = np.asarray(b, np.float64)
    if x.shape != y.shape or x.ndim != 2:
        raise ValueError(f"SSIM needs two 2-D images of one shape, got {x.shape} and {y.shape}")
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    mx, my = _gauss(x, sigma), _gauss(y, sigma)
    vx = _gauss(x * x, sigma) - mx * mx
    vy = _gauss(y * y, sigma) - my * my
    cxy = _gauss(x * y, sigma) - mx * my
    lum = (2 * mx * my + c1) / (mx * mx + my * my + c1)
    cs = (2 * cxy + c2) / (np.maximum(vx, 0) + np.maximum(vy, 0) + c2)
    return lum, cs


def ssim(pred: NDArray[np.generic], target: NDArray[np.generic], data_range: float = 255.0) -> float:
    """Mean SSIM of two gray images."""
    lum, cs = ssim_components(pred, target, data_range)
    return float(np.mean(lum * cs))


def affine_align(pred: NDArray[np.generic], target: NDArray[np.generic]) -> F64:
    """pred mapped by the least-squares scale and offset onto target.

    For reconstructions known only up to an affine map of intensity (event integration without a
    reference frame), as the 'normalised' columns of EVREAL-style tables.
    """
    a = np.asarray(pred, np.float64).ravel()
    b = np.asarray(target, np.float64).ravel()
    var = float(a.var())
    scale = float(np.mean((a - a.mean()) * (b - b.mean())) / var) if var > 0 else 0.0
    return (np.asarray(pred, np.float64) - a.mean()) * scale + b.mean()
