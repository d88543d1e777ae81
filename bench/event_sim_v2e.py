"""Event simulator against v2e's EventEmulator on the same frames: `python -m bench.event_sim_v2e`.

A textured image (bench.event_sim's texture) translates at SPEED px per frame, 30 FPS,
rendered at 1280x720 by default, as 8-bit frames like a video's (`--dtype float32`: the
float render, 0-255). The same frames go to v2e's
`v2ecore.emulator.EventEmulator` (torch on the CPU) and to `firmware_sim.event_model.
EventSimulator`, both configured alike, in two settings:

* noise off: ON/OFF thresholds 0.2, no mismatch, no low-pass, leak, shot noise or
  refractory period;
* v2e default noise: the defaults of v2e's command line (`v2e --help`): thresholds 0.2,
  sigma 0.03, photoreceptor cut-off 300 Hz (intensity dependent), leak 0.01 Hz, shot noise
  0.001 Hz, refractory period 0.5 ms.

Times are wall seconds for the frames after the first (the first only sets the state, in
both), best of --repeats runs, numba compilation and v2e's first run excluded (warmed up
first). Ours runs on 1 and on 2 numba threads (`numba.set_num_threads`); v2e on torch's default thread count
(printed). The models differ in detail (v2e stamps a pixel's events on a shared time grid
and gives its leak a per-pixel rate spread, ours interpolates each crossing), so event
counts are close, not equal.

v2e is optional (not on PyPI) and runs in a venv of its own, in a process of its own
(bench/v2e_peer_worker.py; rigd's numba threads and torch's never share a process), fed the
same frames through a .npy file, given as `--peer-python` (default /tmp/scratch-perf/bin/python):

    python3 -m venv /tmp/scratch-perf && /tmp/scratch-perf/bin/pip install torch numba \
        engineering-notation screeninfo easygui opencv-python-headless scipy tqdm h5py
    git clone https://github.com/SensorsINI/v2e /tmp/v2e-src
    echo /tmp/v2e-src > /tmp/scratch-perf/lib/python3.11/site-packages/v2e-src.pth

Without it the v2e columns are skipped (with a message).
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from bench.event_sim import FPS, make_texture, render
from bench.peer_process import PeerProcess
from firmware_sim.event_model import EventSimulator, PixelModelConfig

log = logging.getLogger(__name__)
WORKER = Path(__file__).resolve().with_name("v2e_peer_worker.py")

MAX_THREADS: int = numba.config.NUMBA_NUM_THREADS  # type: ignore[attr-defined]


@dataclass(frozen=True)
class Setting:
    name: str
    ours: PixelModelConfig
    v2e: dict[str, Any]


SETTINGS = [
    Setting(
        "noise off",
        PixelModelConfig(threshold=0.2),
        {
            "pos_thres": 0.2,
            "neg_thres": 0.2,
            "sigma_thres": 0.0,
            "cutoff_hz": 0.0,
            "leak_rate_hz": 0.0,
            "shot_noise_rate_hz": 0.0,
            "refractory_period_s": 0.0,
        },
    ),
    Setting(
        "v2e default noise",
        PixelModelConfig(
            threshold=0.2,
            sigma=0.03,
            lowpass=True,
            lowpass_cutoff_hz=300.0,
            leak_rate_hz=0.01,
            shot_noise_rate_hz=0.001,
            refractory_us=500,
        ),
        {
            "pos_thres": 0.2,
            "neg_thres": 0.2,
            "sigma_thres": 0.03,
            "cutoff_hz": 300.0,
            "leak_rate_hz": 0.01,
            "shot_noise_rate_hz": 0.001,
            "refractory_period_s": 0.0005,
        },
    ),
]


class V2eWorker:
    """v2e's EventEmulator in its own process and venv (bench/v2e_peer_worker.py), fed the
    parent's frames through a .npy file; one timed run per request."""

    def __init__(self, python: Path, frames: list[NDArray[Any]]) -> None:
        self._dir = tempfile.TemporaryDirectory(prefix="rigd-v2e-")
        path = Path(self._dir.name) / "frames.npy"
        np.save(path, np.stack(frames))
        self._peer = PeerProcess([str(python), str(WORKER), str(path), str(FPS)])
        self.note: str = self._peer.hello["note"]

    def run(self, kwargs: dict[str, Any]) -> tuple[float, int]:
        return self._peer.run(json.dumps(kwargs))

    def close(self) -> None:
        self._peer.close()
        self._dir.cleanup()


def time_ours(cfg: PixelModelConfig, frames: list[NDArray[Any]], threads: int) -> tuple[float, int]:
    numba.set_num_threads(threads)
    h, w = frames[0].shape
    dt = round(1e6 / FPS)
    sim = EventSimulator(w, h, cfg)
    sim.step(frames[0], 0)
    n = 0
    t0 = time.perf_counter()
    for i, f in enumerate(frames[1:], start=1):
        n += len(sim.step(f, i * dt))
    return time.perf_counter() - t0, n


def warm_up(cfg: PixelModelConfig, dtype: str) -> None:
    """Compile (or load from numba's cache) every kernel the step uses, on 1 and 2 threads."""
    rng = np.random.default_rng(0)
    small = [rng.uniform(0, 255, (24, 32)).astype(dtype) for _ in range(3)]
    for threads in (1, min(2, MAX_THREADS)):
        numba.set_num_threads(threads)
        sim = EventSimulator(32, 24, cfg)
        for i, f in enumerate(small):
            sim.step(f, i * 33_333)


def run(
    width: int, height: int, n_frames: int, speed: float, repeats: int, dtype: str, peer_python: Path
) -> None:
    two = min(2, MAX_THREADS)
    tex = make_texture(width, height, int(speed * n_frames) + 16)
    frames: list[NDArray[Any]] = [render(tex, -speed * i, width) for i in range(n_frames)]
    if dtype == "uint8":
        frames = [np.round(f).astype(np.uint8) for f in frames]
    emulator: V2eWorker | None = None
    if peer_python.exists():
        emulator = V2eWorker(peer_python, frames)
        note = emulator.note
    else:
        note = f"v2e: {peer_python} not found; v2e columns skipped (install: see this module's docstring)"
    mpix = width * height * (n_frames - 1) / 1e6
    print(
        f"scene: {width}x{height} {dtype} frames, {n_frames} frames at {FPS:.0f} FPS, "
        f"motion {speed:g} px/frame; best of {repeats}; "
        f"numba {numba.__version__} ({MAX_THREADS} threads available)"
    )
    print(note)
    header = (
        f"{'setting':<19}{'frames':>7}{'v2e s':>8}{'rigd 1T s':>10}{f'rigd {two}T s':>10}"
        f"{'v2e Mpix/s':>11}{'1T Mpix/s':>10}{f'{two}T Mpix/s':>10}"
        f"{'v2e events':>12}{'rigd events':>12}{'v2e/1T':>8}{f'v2e/{two}T':>8}"
    )
    print(header)
    print("-" * len(header))
    for s in SETTINGS:
        warm_up(s.ours, dtype)
        best_v2e = best_1 = best_2 = float("inf")
        ev_v2e = ev_ours = 0
        if emulator is not None:
            emulator.run(s.v2e)  # warm-up: torch's first calls, page cache
        for _ in range(repeats):  # interleaved, so both see the same load on a shared machine
            if emulator is not None:
                wall, ev_v2e = emulator.run(s.v2e)
                best_v2e = min(best_v2e, wall)
            wall, ev_ours = time_ours(s.ours, frames, 1)
            best_1 = min(best_1, wall)
            wall, ev_two = time_ours(s.ours, frames, two)
            best_2 = min(best_2, wall)
            if ev_two != ev_ours:
                raise AssertionError(f"{s.name}: {ev_two} events on {two} threads, {ev_ours} on 1")
        if emulator is not None:
            v2e_cols = f"{best_v2e:>8.2f}"
            v2e_rate = f"{mpix / best_v2e:>11.1f}"
            v2e_ev = f"{ev_v2e:>12,}"
            ratios = f"{best_v2e / best_1:>7.1f}x{best_v2e / best_2:>7.1f}x"
        else:
            v2e_cols, v2e_rate, v2e_ev, ratios = f"{'-':>8}", f"{'-':>11}", f"{'-':>12}", f"{'-':>8}{'-':>8}"
        print(
            f"{s.name:<19}{n_frames - 1:>7}{v2e_cols}{best_1:>10.3f}{best_2:>10.3f}"
            f"{v2e_rate}{mpix / best_1:>10.1f}{mpix / best_2:>10.1f}{v2e_ev}{ev_ours:>12,}{ratios}"
        )
    numba.set_num_threads(MAX_THREADS)
    if emulator is not None:
        emulator.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--frames", type=int, default=30, help="frames rendered (the first only sets the state)")
    ap.add_argument("--speed", type=float, default=6.0, help="px per frame")
    ap.add_argument("--repeats", type=int, default=2, help="runs per setting; the best is shown")
    ap.add_argument("--dtype", choices=["uint8", "float32"], default="uint8", help="frame type fed to both")
    ap.add_argument(
        "--peer-python",
        type=Path,
        default=Path("/tmp/scratch-perf/bin/python"),
        help="python of v2e's own venv (torch, numba, v2e's source on its path)",
    )
    args = ap.parse_args()
    if args.frames < 2:
        ap.error("--frames must be at least 2")
    run(args.width, args.height, args.frames, args.speed, args.repeats, args.dtype, args.peer_python)


if __name__ == "__main__":
    main()
