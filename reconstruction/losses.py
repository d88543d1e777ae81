"""The paper's training losses (Eqs. 6-8), in numpy and, when torch is installed, in torch.

* `l1`: mean absolute error (the RGB term and, between a rendering and the flow-warped event
  image, the flow loss of Eq. 7: `flow_loss`).
* `structure_ssim_loss`: 1 - (contrast-structure part of SSIM), Eq. 6. The luminance term is left
  out on purpose: event-derived images have no reliable absolute brightness, only structure.
* `spatiotemporal_tv`: Eq. 8, sum over pixels of sqrt(|grad_xy C|^2 + beta^2 |grad_t C|^2) on a
  (T, H, W) or (T, C, H, W) stack, averaged here so its scale does not depend on image size.

The numpy versions are the reference for tests and for evaluation code; the torch versions (same
names in `reconstruction.losses.torch_losses()`) are differentiable for a trainer. torch is an
optional dependency: `pip install rigd[torch]`.
"""

from __future__ import annotations

import logging
from types import SimpleNamespace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from reconstruction.metrics import ssim_components

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


def l1(
    pred: NDArray[np.generic], target: NDArray[np.generic], mask: NDArray[np.bool_] | None = None
) -> float:
    """Mean |pred - target| (over `mask` when given)."""
    d = np.abs(np.asarray(pred, np.float64) - np.asarray(target, np.float64))
    if mask is not None:
        m = np.broadcast_to(np.asarray(mask, bool), d.shape)
        return float(d[m].mean()) if m.any() else 0.0
    return float(d.mean())


def flow_loss(
    rendered: NDArray[np.generic],
    warped_event_image: NDArray[np.generic],
    valid: NDArray[np.bool_] | None = None,
) -> float:
    """Eq. 7: L1 between the rendering at t' and the event image warped to t' (valid pixels only)."""
    return l1(rendered, warped_event_image, valid)


def structure_ssim_loss(
    pred: NDArray[np.generic], target: NDArray[np.generic], data_range: float = 1.0
) -> float:
    """Eq. 6: mean of 1 - SSIM's contrast-structure term (brightness-invariant)."""
    _, cs = ssim_components(pred, target, data_range)
    return float(np.mean(1.0 - cs))


def spatiotemporal_tv(stack: NDArray[np.generic], beta: float = 1.0, eps: float = 1e-8) -> float:
    """Eq. 8 on a (T, H, W) or (T, C, H, W) stack, mean over the grid of forward differences."""
    c = np.asarray(stack, np.float64)
    if c.ndim == 3:
        c = c[:, None]
    if c.ndim != 4 or c.shape[0] < 2:
        raise ValueError(f"need a (T>=2, [C,] H, W) stack, got shape {np.shape(stack)}")
    gx = c[:-1, :, :-1, 1:] - c[:-1, :, :-1, :-1]
    gy = c[:-1, :, 1:, :-1] - c[:-1, :, :-1, :-1]
    gt = c[1:, :, :-1, :-1] - c[:-1, :, :-1, :-1]
    return float(np.mean(np.sqrt(gx * gx + gy * gy + beta * beta * gt * gt + eps)))


def torch_losses() -> SimpleNamespace:
    """Differentiable torch versions: l1, flow_loss, structure_ssim_loss, spatiotemporal_tv.

    Raises ImportError with an install hint when torch is missing (it is optional).
    """
    try:
        import torch
        import torch.nn.functional as tf
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            "torch losses need PyTorch: pip install 'rigd[torch]' (or pip install torch)"
        ) from exc

    def _l1(pred: Any, target: Any, mask: Any = None) -> Any:
        d = (pred - target).abs()
        if mask is not None:
            m = mask.expand_as(d).to(d.dtype)
            return (d * m).sum() / m.sum().clamp_min(1.0)
        return d.mean()

    def _gauss_window(sigma: float, device: Any, dtype: Any) -> Any:
        r = round(4 * sigma)
        x = torch.arange(-r, r + 1, device=device, dtype=dtype)
        g = torch.exp(-(x * x) / (2 * sigma * sigma))
        return g / g.sum()

    def _blur(img: Any, g: Any) -> Any:
        c = img.shape[1]
        k = g.numel()
        pad = k // 2
        img = tf.pad(img, (pad, pad, pad, pad), mode="reflect")
        img = tf.conv2d(img, g.view(1, 1, 1, k).expand(c, 1, 1, k), groups=c)
        return tf.conv2d(img, g.view(1, 1, k, 1).expand(c, 1, k, 1), groups=c)

    def _as4d(img: Any) -> Any:
        if img.dim() == 2:
            return img[None, None]
        if img.dim() == 3:
            return img[None]
        return img

    def _struct(pred: Any, target: Any, data_range: float = 1.0, sigma: float = 1.5) -> Any:
        """pred, target: (H, W), (C, H, W) or (N, C, H, W), like the numpy version."""
        pred, target = _as4d(pred), _as4d(target)
        g = _gauss_window(sigma, pred.device, pred.dtype)
        mx, my = _blur(pred, g), _blur(target, g)
        vx = _blur(pred * pred, g) - mx * mx
        vy = _blur(target * target, g) - my * my
        cxy = _blur(pred * target, g) - mx * my
        c2 = (0.03 * data_range) ** 2
        cs = (2 * cxy + c2) / (vx.clamp_min(0) + vy.clamp_min(0) + c2)
        return (1 - cs).mean()

    def _tv(stack: Any, beta: float = 1.0, eps: float = 1e-8) -> Any:
        c = stack if stack.dim() == 4 else stack.unsqueeze(1)
        gx = c[:-1, :, :-1, 1:] - c[:-1, :, :-1, :-1]
        gy = c[:-1, :, 1:, :-1] - c[:-1, :, :-1, :-1]
        gt = c[1:, :, :-1, :-1] - c[:-1, :, :-1, :-1]
        return torch.sqrt(gx * gx + gy * gy + beta * beta * gt * gt + eps).mean()

    return SimpleNamespace(l1=_l1, flow_loss=_l1, structure_ssim_loss=_struct, spatiotemporal_tv=_tv)
