"""Synthetic sequences with ground truth for the reconstruction tests and benchmarks.

A static textured background and textured square sprites moving along given paths, rendered in
linear intensity (DN 0..255) at any time; events come from the project's pixel model
(`firmware_sim.event_model.EventSimulator`) stepped on frames rendered finely enough that motion
per step stays under `max_px_per_step`, so the events are those of the continuous motion.
Ground truth: intensity frames at any time, the motion region (union of sprite boxes), and the
exact flow of a global translation (`translate`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from firmware_sim.event_model import EventSimulator, PixelModelConfig
from rigd.core.events import EventArray

F32 = NDArray[np.float32]
Path = Callable[[float], tuple[float, float]]
"""Sprite top-left (x, y) in px at time t (seconds)."""


def texture(h: int, w: int, seed: int = 0, cell: int = 6, lo: float = 30.0, hi: float = 220.0) -> F32:
    """Smooth random texture with sharp-ish detail, DN lo..hi."""
    rng = np.random.default_rng(seed)
    small = rng.uniform(0, 1, (h // cell + 2, w // cell + 2)).astype(np.float32)
    img = cv2.resize(small, (w + 2 * cell, h + 2 * cell), interpolation=cv2.INTER_CUBIC)[
        cell:-cell, cell:-cell
    ]
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    img = (img - img.min()) / max(float(img.max() - img.min()), 1e-6)
    return np.ascontiguousarray(lo + (hi - lo) * img, dtype=np.float32)


@dataclass
class SpriteScene:
    """Background + sprites moving along paths; `render(t_s)` gives linear intensity."""

    width: int
    height: int
    paths: list[Path]
    sprite_px: int = 40
    seed: int = 0

    def __post_init__(self) -> None:
        self.bg = texture(self.height, self.width, self.seed, cell=10, lo=60, hi=140)
        self.sprites = [
            texture(self.sprite_px, self.sprite_px, self.seed + 1 + i, cell=5, lo=10, hi=250)
            for i in range(len(self.paths))
        ]

    def render(self, t_s: float) -> F32:
        out = self.bg.copy()
        for spr, path in zip(self.sprites, self.paths, strict=True):
            x, y = path(t_s)
            m = np.array([[1, 0, x], [0, 1, y]], np.float32)
            warped = cv2.warpAffine(spr, m, (self.width, self.height), flags=cv2.INTER_LINEAR)
            alpha = cv2.warpAffine(np.ones_like(spr), m, (self.width, self.height), flags=cv2.INTER_LINEAR)
            out = out * (1 - alpha) + warped
        return out.astype(np.float32)

    def motion_mask(self, t0_s: float, t1_s: float, n: int = 8) -> NDArray[np.bool_]:
        """Pixels covered by some sprite at some time in [t0, t1] (the motion region)."""
        mask = np.zeros((self.height, self.width), bool)
        for path in self.paths:
            for t in np.linspace(t0_s, t1_s, n):
                x, y = path(float(t))
                x0, y0 = max(math.floor(x), 0), max(math.floor(y), 0)
                mask[y0 : math.ceil(y + self.sprite_px) + 1, x0 : math.ceil(x + self.sprite_px) + 1] = True
        return mask

    def speed_px_s(self, t_s: float, dt: float = 1e-4) -> float:
        return (
            max(math.hypot(p(t_s + dt)[0] - p(t_s)[0], p(t_s + dt)[1] - p(t_s)[1]) / dt for p in self.paths)
            if self.paths
            else 0.0
        )


def simulate(
    scene: SpriteScene,
    t0_s: float,
    t1_s: float,
    *,
    threshold: float = 0.15,
    max_px_per_step: float = 0.5,
    min_step_us: int = 100,
    max_step_us: int = 2000,
    shot_noise_rate_hz: float = 0.0,
    seed: int = 0,
    t_offset_us: int = 0,
) -> EventArray:
    """Events of the scene over [t0, t1] from the pixel model, adaptive steps by sprite speed."""
    cfg = PixelModelConfig(threshold=threshold, shot_noise_rate_hz=shot_noise_rate_hz, seed=seed)
    sim = EventSimulator(scene.width, scene.height, cfg)
    t_us = round(t0_s * 1e6)
    end_us = round(t1_s * 1e6)
    parts = []
    sim.step(scene.render(t_us * 1e-6), t_us + t_offset_us)
    while t_us < end_us:
        v = scene.speed_px_s(t_us * 1e-6)
        step = max_step_us if v <= 0 else int(np.clip(max_px_per_step / v * 1e6, min_step_us, max_step_us))
        t_us = min(t_us + step, end_us)
        parts.append(sim.step(scene.render(t_us * 1e-6), t_us + t_offset_us))
    return EventArray.concatenate(parts)


def linear_path(x0: float, y0: float, vx: float, vy: float) -> Path:
    return lambda t: (x0 + vx * t, y0 + vy * t)


def translate(img: F32, dx: float, dy: float) -> F32:
    """img shifted by (dx, dy): out(x, y) = img(x - dx, y - dy); the flow img -> out is (dx, dy)."""
    m = np.array([[1, 0, dx], [0, 1, dy]], np.float32)
    out = cv2.warpAffine(
        img, m, (img.shape[1], img.shape[0]), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT
    )
    return np.asarray(out, np.float32)
