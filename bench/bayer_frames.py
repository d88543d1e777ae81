"""bayer_rg8 against rgb8: bytes per frame, the take writer's frame rate and MB/s, and what the
demosaic on read costs.

    python -m bench.bayer_frames [--frames 90] [--width 1280] [--height 720] [--repeat 3] [--dir DIR]

Frames are the simulator's own renders of its sprite scene (three cameras' views), written
through `TakeWriter.append_frame` as a capture's writer thread does (default writer config:
frames uncompressed, flushed at the end with fsync), as RGB and as their RGGB mosaics,
alternating (`--repeat` times each, the best kept: on a shared machine the spread is large).
The demosaic rows time `rigd.core.pixels` (edge-aware: what every reader of a Bayer take pays
per frame) beside OpenCV's bilinear and VNG variants, and the sim's mosaic.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from firmware_sim.scene import Scene
from rigd.core.devices import DeviceInfo
from rigd.core.frames import Frame
from rigd.core.pixels import demosaic, demosaic_gray, mosaic_rggb
from rigd.core.settings import WriterConfig
from rigd.take import TakeWriter

CAMERAS = ("cam0", "cam1", "cam2")
RATE_HZ = 30.0


def renders(n: int, width: int, height: int) -> dict[str, list[NDArray[np.uint8]]]:
    """n RGB frames per camera at 30 Hz of the sim's sprite scene."""
    scene = Scene(seed=0)
    views = {c: scene.view(c, width, height) for c in CAMERAS}
    return {c: [scene.render(views[c], i * 1e6 / RATE_HZ) for i in range(n)] for c in CAMERAS}


def write(path: Path, frames: dict[str, list[NDArray[np.uint8]]], fmt: str) -> tuple[float, int]:
    """(seconds to append every frame and flush, bytes of the take file)."""
    w = TakeWriter(path, rig_config_json="{}", take_id=fmt, config=WriterConfig(), rigd_version="bench")
    for c, fr in frames.items():
        w.add_camera(c, DeviceInfo(kind="rgb_camera", spec="bench"), fr[0].shape, np.uint8, "{}", fmt)
    n = len(frames[CAMERAS[0]])
    t0 = time.perf_counter()
    for i in range(n):
        for c in CAMERAS:
            w.append_frame(
                c, Frame(frames[c][i], 1_000_000 + round(i * 1e6 / RATE_HZ), 8000, i, i, pixel_format=fmt)
            )
    w.flush()
    dt = time.perf_counter() - t0
    w.close()
    return dt, path.stat().st_size


def per_call_ms(
    fn: Callable[[NDArray[np.uint8]], object], images: list[NDArray[np.uint8]], repeat: int
) -> float:
    """Best of `repeat` passes over the images, ms per image."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for img in images:
            fn(img)
        best = min(best, (time.perf_counter() - t0) / len(images))
    return best * 1e3


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--frames", type=int, default=90, help="frames per camera (90 = 3 s at 30 Hz)")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--repeat", type=int, default=3, help="write / demosaic passes; the best is kept")
    ap.add_argument("--dir", type=Path, default=None, help="Where to write (default: a temp dir).")
    args = ap.parse_args(argv)

    rgb = renders(args.frames, args.width, args.height)
    mosaics = {c: [mosaic_rggb(f) for f in fr] for c, fr in rgb.items()}
    n_frames = args.frames * len(CAMERAS)
    print(
        f"{len(CAMERAS)} cameras x {args.frames} frames of {args.width}x{args.height} (sim renders), "
        f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}; best of {args.repeat}"
    )
    print(
        f"{'format':<11}{'B/frame':>11}{'3 cams @30 Hz MB/s':>20}{'append ms/frame':>17}"
        f"{'writer MB/s':>13}{'take MB':>9}"
    )
    formats = {"rgb8": rgb, "bayer_rg8": mosaics}
    best: dict[str, tuple[float, int]] = {}
    with tempfile.TemporaryDirectory(prefix="rigd-bayer-", dir=args.dir) as tmp:
        for k in range(args.repeat):  # alternating, so both see the same load and page cache
            for fmt, frames in formats.items():
                path = Path(tmp) / f"{fmt}-{k}.h5"
                run = write(path, frames, fmt)
                path.unlink()
                best[fmt] = min(best.get(fmt, run), run)
    for fmt, frames in formats.items():
        dt, size = best[fmt]
        frame_bytes = frames[CAMERAS[0]][0].nbytes
        print(
            f"{fmt:<11}{frame_bytes:>11,}{frame_bytes * len(CAMERAS) * RATE_HZ / 1e6:>20.1f}"
            f"{dt / n_frames * 1e3:>17.2f}{frame_bytes * n_frames / dt / 1e6:>13.1f}{size / 1e6:>9.1f}"
        )
    some = mosaics[CAMERAS[0]][: min(30, args.frames)]
    rows = [
        ("demosaic to RGB (rigd.core.pixels, edge-aware)", per_call_ms(demosaic, some, args.repeat)),
        ("demosaic to gray (calibration)", per_call_ms(demosaic_gray, some, args.repeat)),
        (
            "OpenCV bilinear (BayerBG2RGB)",
            per_call_ms(lambda m: cv2.cvtColor(m, cv2.COLOR_BayerBG2RGB), some, args.repeat),
        ),
        (
            "OpenCV VNG (BayerBG2RGB_VNG)",
            per_call_ms(lambda m: cv2.cvtColor(m, cv2.COLOR_BayerBG2RGB_VNG), some, args.repeat),
        ),
        (
            "mosaic of an RGB render (sim)",
            per_call_ms(mosaic_rggb, rgb[CAMERAS[0]][: len(some)], args.repeat),
        ),
    ]
    print(f"{'per frame, ' + str(args.width) + 'x' + str(args.height):<48}{'ms':>8}")
    for name, ms in rows:
        print(f"{name:<48}{ms:>8.2f}")


if __name__ == "__main__":
    main()
