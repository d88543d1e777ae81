"""e2i snapshot quality per method and flow end-point error per preset, with time, on synthetic scenes.

e2i: a simulated 240x180 sequence (oscillating sprites, contrast 0.15, 1 s); snapshots every 10 ms
vs ground-truth log intensity; PSNR/SSIM after a least-squares affine alignment (the methods
without frames know intensity only up to scale/offset). Complementary uses 30 FPS frames.
Flow: a texture translated by known sub-pixel shifts, EPE inside a 16 px border.

    python -m bench.reconstruction_e2i_flow
"""

from __future__ import annotations

import time

import numpy as np

from bench.reconstruction_interp import THRESHOLD, H, W, make_scene
from firmware_sim.testing.sprites import simulate, texture, translate
from reconstruction.e2i import METHODS, log_intensity, reconstruct
from reconstruction.flow import PRESETS, FlowEstimator, endpoint_error
from reconstruction.metrics import affine_align, psnr, ssim


def bench_e2i() -> None:
    scene = make_scene(400.0)
    ev = simulate(scene, 0.0, 1.0, threshold=THRESHOLD)
    times = np.arange(50_000, 1_000_001, 10_000)
    ftimes = np.arange(0, 1_000_001, 33_333)
    frames = [scene.render(t * 1e-6) for t in ftimes]
    gt = [log_intensity(scene.render(t * 1e-6)) for t in times]
    print(f"\ne2i: {len(ev)} events, {len(times)} snapshots, {W}x{H}")
    print(f"| {'method':14s} | {'cutoff Hz':>9s} | {'PSNR dB':>8s} | {'SSIM':>6s} | {'Mev/s':>7s} |")
    print(f"|{'-' * 16}|{'-' * 11}|{'-' * 10}|{'-' * 8}|{'-' * 9}|")
    for m in METHODS:
        for fc in [0.0] if m == "direct" else [1.0, 5.0, 20.0]:
            tic = time.perf_counter()
            snaps = reconstruct(
                ev,
                W,
                H,
                times,
                m,
                frames=frames,
                frame_times_us=ftimes,
                contrast=THRESHOLD,
                init_frame=frames[0],
                cutoff_hz=max(fc, 1e-3),
            )
            dt = time.perf_counter() - tic
            rng = float(np.ptp(gt[0]))
            p = np.mean([psnr(affine_align(s, g), g, data_range=rng) for s, g in zip(snaps, gt, strict=True)])
            s_ = np.mean(
                [ssim(affine_align(s, g), g, data_range=rng) for s, g in zip(snaps, gt, strict=True)]
            )
            print(f"| {m:14s} | {fc:9.1f} | {p:8.2f} | {s_:6.3f} | {len(ev) / dt / 1e6:7.1f} |")


def bench_flow() -> None:
    img = texture(180, 240, seed=5)
    inner = np.zeros(img.shape, bool)
    inner[16:-16, 16:-16] = True
    shifts = [(0.5, 0.25), (2.0, -1.0), (5.0, 3.0), (12.0, -6.0)]
    print(f"\nflow: texture {img.shape[1]}x{img.shape[0]}, translations {shifts}")
    print(f"| {'preset':14s} | " + " | ".join(f"EPE {dx:g},{dy:g}" for dx, dy in shifts) + " | ms/pair |")
    for preset in PRESETS:
        est = FlowEstimator(preset)
        errs, dt = [], 0.0
        for dx, dy in shifts:
            moved = translate(img, dx, dy)
            tic = time.perf_counter()
            f = est(img, moved)
            dt += time.perf_counter() - tic
            errs.append(endpoint_error(f, np.broadcast_to(np.float32([dx, dy]), f.shape), inner))
        cells = " | ".join(
            f"{e:{len(f'EPE {dx:g},{dy:g}')}.3f}" for e, (dx, dy) in zip(errs, shifts, strict=True)
        )
        print(f"| {preset:14s} | {cells} | {1e3 * dt / len(shifts):7.2f} |")


if __name__ == "__main__":
    bench_flow()
    bench_e2i()
