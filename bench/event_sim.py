"""Event simulator speed/accuracy trade: `python -m bench.event_sim`.

A textured image translates at SPEED px per input frame (30 FPS). The reference is the
pixel model fed with the exact image rendered at REF_SUBSTEPS sub-steps per frame (no
flow); each setting instead sees only the input frames and sub-steps them with
flow-based interpolation. Events are matched per (pixel, polarity) in order, and the
timing error is the |t - t_ref| of matched events. Throughput is input pixels x frames
per second of wall time, flow and interpolation included (numba compilation excluded).
"""

from __future__ import annotations

import argparse
import logging
import time

import cv2
import numpy as np
from numpy.typing import NDArray

from firmware_sim.event_model import EventSimulator, PixelModelConfig
from firmware_sim.frames_to_events import FramesToEvents
from rigd.core.events import EventArray

log = logging.getLogger(__name__)

FPS = 30.0
REF_SUBSTEPS = 64


def make_texture(w: int, h: int, margin: int, seed: int = 0) -> NDArray[np.float32]:
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (h, w + margin)).astype(np.float32), (0, 0), 2.5)
    return np.clip((tex - tex.mean()) * 5 + 128, 5, 250).astype(np.float32)


def render(tex: NDArray[np.float32], x: float, w: int) -> NDArray[np.float32]:
    m = np.array([[1, 0, x], [0, 1, 0]], np.float32)
    return np.asarray(cv2.warpAffine(tex, m, (w, tex.shape[0]), flags=cv2.INTER_LINEAR), np.float32)


def match_errors(ev: EventArray, ref: EventArray, width: int) -> tuple[NDArray[np.float64], int]:
    """|t - t_ref| of events matched by (pixel, polarity, k-th occurrence); and the matched count."""

    def keyed(e: EventArray) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        grp = (e.y.astype(np.int64) * width + e.x) * 2 + (e.p > 0)
        order = np.lexsort((e.t, grp))
        g, t = grp[order], e.t[order]
        start = np.r_[0, np.flatnonzero(np.diff(g)) + 1]
        rank = np.arange(g.size) - np.repeat(start, np.diff(np.r_[start, g.size]))
        return g * 100_000 + rank, t

    k1, t1 = keyed(ev)
    k2, t2 = keyed(ref)
    order = np.argsort(k2)
    k2, t2 = k2[order], t2[order]
    pos = np.clip(np.searchsorted(k2, k1), 0, max(k2.size - 1, 0))
    hit = k2[pos] == k1 if k2.size else np.zeros(k1.size, bool)
    return np.abs(t1[hit] - t2[pos[hit]]).astype(np.float64), int(hit.sum())


def run(width: int, height: int, n_frames: int, speed: float) -> None:
    cfg = PixelModelConfig(threshold=0.3)
    tex = make_texture(width, height, int(speed * n_frames) + 16)
    dt = round(1e6 / FPS)
    frames = [render(tex, -speed * i, width) for i in range(n_frames)]
    # Warm up numba (compiled once, cached) so timings are steady-state.
    warm = FramesToEvents(width, height, cfg, substeps=2)
    for i in range(2):
        warm.push(frames[i], i * dt)

    ref_sim = EventSimulator(width, height, cfg)
    parts = [ref_sim.step(frames[0], 0)]
    t0 = time.perf_counter()
    for i in range(1, n_frames):
        for j in range(1, REF_SUBSTEPS + 1):
            x = -speed * (i - 1 + j / REF_SUBSTEPS)
            parts.append(ref_sim.step(render(tex, x, width), (i - 1) * dt + round(j * dt / REF_SUBSTEPS)))
    ref = EventArray.concatenate(parts)
    ref_wall = time.perf_counter() - t0
    print(
        f"scene: {width}x{height}, {n_frames} frames at {FPS:.0f} FPS, motion {speed:g} px/frame; "
        f"reference: exact renders, {REF_SUBSTEPS} sub-steps/frame, {len(ref)} events "
        f"(pixel model alone: {width * height * (n_frames - 1) * REF_SUBSTEPS / ref_wall / 1e6:.0f} "
        "Mpix-steps/s incl. rendering)"
    )
    header = (
        f"{'setting':<22}{'sub-steps':>10}{'Mpix-frames/s':>15}{'events/ref':>12}"
        f"{'matched':>9}{'median |dt| us':>16}{'p90 |dt| us':>13}"
    )
    print(header)
    print("-" * len(header))
    settings: list[tuple[str, dict[str, float | int]]] = [
        ("fixed 1 (no interp.)", {"substeps": 1}),
        ("fixed 2", {"substeps": 2}),
        ("fixed 4", {"substeps": 4}),
        ("fixed 8", {"substeps": 8}),
        ("adaptive <= 1 px", {"max_px_per_step": 1.0}),
        ("adaptive <= 0.5 px", {"max_px_per_step": 0.5}),
    ]
    for name, kw in settings:
        f2e = FramesToEvents(width, height, cfg, **kw)  # type: ignore[arg-type]
        t0 = time.perf_counter()
        out = EventArray.concatenate([f2e.push(f, i * dt).events for i, f in enumerate(frames)])
        wall = time.perf_counter() - t0
        err, matched = match_errors(out, ref, width)
        mean_sub = f2e.substeps_total / (n_frames - 1)
        print(
            f"{name:<22}{mean_sub:>10.1f}{width * height * n_frames / wall / 1e6:>15.1f}"
            f"{len(out) / max(len(ref), 1):>12.2f}{matched / max(len(ref), 1):>9.2f}"
            f"{np.median(err) if err.size else float('nan'):>16.0f}"
            f"{np.percentile(err, 90) if err.size else float('nan'):>13.0f}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--speed", type=float, default=6.0, help="px per input frame")
    args = ap.parse_args()
    run(args.width, args.height, args.frames, args.speed)


if __name__ == "__main__":
    main()
