"""Training reader: samples/s of random 50 ms windows per worker count and representation.

    python -m bench.training_reader [--quick] [--device auto|cpu|cuda] [--workers 0,2,4]
                                    [--batch 8] [--take TAKE.h5 | --take-dir DIR] [--json OUT]

The take is a dense one recorded on the simulator's virtual clock (the default sim rig with one
1280x720 event sensor at ~1.3 Mev/s, i.e. ~65 000 events a 50 ms window, and one 720p rgb8
camera), or the take given. Every cell is a `torch.utils.data.DataLoader` over
`reconstruction.dataset.torch_dataset` with each worker opening the take itself, timed from
the batch after the warm-up ones until the representation is on the device (synchronized):

* `baseline`: the dataset as it was (numpy `np.bincount` voxel grid in the worker, shipped dense);
* `worker`: the same, with the numba voxel grid (and numpy event frame / time surface);
* `device`: the worker ships packed events (9 B an event), the grid is built on the device;
* `events`: packed events only, no representation (the reading ceiling).

With CUDA, the same loaders then feed a small UNet training step (`bench.small_unet`) beside
the model alone on a resident batch: the loader is not the bottleneck when "with model"
reaches "model alone". Without CUDA the model rows are left out (a UNet step at 1280x720 on a
CPU measures the CPU, not the loader). Part 1 times `voxel_grid` (numba) against the numpy
reference on the take's windows, one thread.
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import os
import platform
import shutil
import statistics
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bench.small_unet import ModelStep
from reconstruction.dataset import WindowSampler
from reconstruction.representations import VoxelGridder, voxel_grid, voxel_grid_bincount
from reconstruction.torch_dataset import ReaderOptions, WindowDataset
from rigd.take import Take

log = logging.getLogger(__name__)

SENSOR, CAMERA = "ev0", "cam0"
WINDOW_US, BINS = 50_000, 5
NUMPY_ROW = "voxel_grid_bincount (numpy, before)"
NUMBA_ROW = "voxel_grid (numba, new grid)"
NUMBA_OUT_ROW = "voxel_grid (numba, out= reused grid)"
GRIDDER_ROW = "VoxelGridder (numba, resets what it wrote)"
ZEROS_ROW = "np.zeros of the grid alone (memory floor)"


class BaselineDataset(WindowDataset):
    """The dataset before the training reader: the numpy voxel grid built in the worker."""

    def _dense(self, ev: Any, t0: int, t_last: int) -> Any:
        return voxel_grid_bincount(ev, self.width, self.height, self.bins, t0, t_last)


@dataclass
class Cell:
    """One measured loader: what it delivers, where, with how many workers, and how fast."""

    path: str
    representation: str
    workers: int
    camera: bool
    samples_per_s: float
    shipped_mb: float
    with_model: bool = False


# ----------------------------------------------------------------------------- the take
def record_take(out_dir: Path, seconds: float, seed: int = 0) -> Path:
    """A dense take of the default sim rig on the virtual clock: one event sensor, one camera."""
    from firmware_sim.world import reset_world
    from rigd.app.capture import run_capture
    from rigd.app.config import default_sim_rig

    world = f"bench-tr-{uuid.uuid4().hex[:8]}"
    cfg = default_sim_rig(world=world, seed=seed, clock="virtual")
    cfg.cameras, cfg.event_sensors = cfg.cameras[:1], cfg.event_sensors[:1]
    log.info("recording a %.1f s take on the virtual clock into %s", seconds, out_dir)
    t0 = time.perf_counter()
    try:
        res = run_capture(cfg, out_dir, seconds)
    finally:
        reset_world(world)
    lost = [r for r in res.report.losses if r.count]
    if lost:
        raise RuntimeError(f"the bench take lost data while recording: {lost}")
    log.info("recorded %s in %.1f s", res.path, time.perf_counter() - t0)
    return res.path


def find_or_record(take_dir: Path, seconds: float) -> Path:
    """The newest take in `take_dir` recorded for this bench, or a new one."""
    takes = sorted(take_dir.glob("*.h5"), key=lambda p: p.stat().st_mtime)
    for path in reversed(takes):
        with Take(path) as take:
            span = take.sensor(SENSOR).span if SENSOR in take.event_sensors else None
            if span is not None and take.status == "complete" and span[1] - span[0] >= 0.9 * seconds * 1e6:
                log.info("reusing %s", path)
                return path
    take_dir.mkdir(parents=True, exist_ok=True)
    return record_take(take_dir, seconds)


# ----------------------------------------------------------------------------- loaders
def make_dataset(
    path: Path, kind: str, representation: str, camera: bool, n: int, seed: int
) -> WindowDataset:
    """`kind`: baseline, worker, device or events (device without building a representation)."""
    take = Take(path)
    sampler = WindowSampler(
        take, SENSOR, CAMERA if camera else None, window_us=WINDOW_US, bins=BINS, n_samples=n
    )
    options = ReaderOptions(
        representation=representation,  # type: ignore[arg-type]
        representation_on="worker" if kind in ("baseline", "worker") else "device",
        seed=seed,
    )
    cls = BaselineDataset if kind == "baseline" else WindowDataset
    return cls(sampler, options, functools.partial(Take, path))


def shipped_mb(ds: WindowDataset) -> float:
    """Mean bytes a worker sends per sample (tensors and packed events), over a few items."""
    total = 0
    for i in range(min(4, len(ds))):
        for v in ds[i].values():
            total += v.nbytes if isinstance(v, torch.Tensor) else getattr(v, "nbytes", 0)
    return total / min(4, len(ds)) / 1e6


def batches(ds: WindowDataset, workers: int, batch: int, device: torch.device) -> Iterator[dict[str, Any]]:
    loader = torch.utils.data.DataLoader(
        ds,
        batch_size=batch,
        num_workers=workers,
        collate_fn=ds.collate,
        pin_memory=device.type == "cuda",
        prefetch_factor=4 if workers else None,
        shuffle=False,
    )
    yield from loader


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_loader(
    ds: WindowDataset,
    workers: int,
    batch: int,
    device: torch.device,
    warmup: int,
    step: Callable[[dict[str, Any]], None] | None,
    build: bool,
) -> float:
    """Samples/s after `warmup` batches: each batch moved to `device` (its representation built
    there when `build`), then given to `step` when there is one."""
    n, t0 = 0, 0.0
    for k, b in enumerate(batches(ds, workers, batch, device)):
        if build:
            b = ds.to_device(b, device)
        else:
            b = {key: v.to(device, non_blocking=True) if hasattr(v, "to") else v for key, v in b.items()}
        if step is not None:
            step(b)
        if k == warmup - 1:
            sync(device)
            t0 = time.perf_counter()
        elif k >= warmup:
            n += int(b["t0_us"].shape[0])
    sync(device)
    return n / (time.perf_counter() - t0)


# ----------------------------------------------------------------------------- parts
def voxel_micro(path: Path, windows: int) -> list[tuple[str, float, float]]:
    """Median and best ms per window, one thread: reading the events alone, the numpy voxel
    grid, the numba one into a new grid, into a reused one (`out=`) and through a `VoxelGridder`,
    and a new zeroed grid with no events: what any dense new grid costs at least. The rows are
    interleaved window by window, in an order rotated each window, so that on a shared host every
    row sees the same load and none always runs after the numpy one has flushed the caches."""
    with Take(path) as take:
        span = take.sensor(SENSOR).span
        assert span is not None
        w, h = take.sensor(SENSOR).geometry
        rng = np.random.default_rng(1)
        starts = rng.integers(span[0], span[1] - WINDOW_US, windows)
        evs, read = [], []
        for t0 in starts:
            s = time.perf_counter()
            evs.append(take.sensor(SENSOR).events(int(t0), int(t0) + WINDOW_US))
            read.append(time.perf_counter() - s)
    rows = [("Take.events (read the window)", statistics.median(read) * 1e3, min(read) * 1e3)]
    buf = np.zeros((BINS, h, w), np.float32)
    gridder = VoxelGridder(w, h, BINS)
    impls: list[tuple[str, Callable[..., Any]]] = [
        (NUMPY_ROW, voxel_grid_bincount),
        (NUMBA_ROW, voxel_grid),
        (NUMBA_OUT_ROW, functools.partial(voxel_grid, out=buf)),
        (GRIDDER_ROW, lambda ev, _w, _h, _b, t0, t1: gridder(ev, t0, t1)),
        (ZEROS_ROW, lambda _ev, w_, h_, b_, _t0, _t1: np.zeros((b_, h_, w_), np.float32)),
    ]
    for _, fn in impls:
        fn(evs[0], w, h, BINS, int(starts[0]), int(starts[0]) + WINDOW_US - 1)  # compile / warm
    times: dict[str, list[float]] = {name: [] for name, _ in impls}
    for k, (ev, t0) in enumerate(zip(evs, starts, strict=True)):
        r = k % len(impls)
        for name, fn in impls[r:] + impls[:r]:
            s = time.perf_counter()
            fn(ev, w, h, BINS, int(t0), int(t0) + WINDOW_US - 1)
            times[name].append(time.perf_counter() - s)
    rows += [(name, statistics.median(ts) * 1e3, min(ts) * 1e3) for name, ts in times.items()]
    rows.append(("events per window (mean)", float(np.mean([len(e) for e in evs])), 0.0))
    return rows


def run_cells(args: argparse.Namespace, path: Path, device: torch.device) -> list[Cell]:
    cells: list[Cell] = []
    per_cell = (args.warmup + args.batches) * args.batch
    plan: list[tuple[str, str, bool]] = [("baseline", "voxel_grid", False), ("worker", "voxel_grid", False)]
    plan += [("device", "voxel_grid", False), ("events", "voxel_grid", False), ("device", "voxel_grid", True)]
    plan += [(k, r, False) for r in ("event_frame", "time_surface") for k in ("worker", "device")]
    for kind, rep, camera in plan:
        workers = args.workers if (rep == "voxel_grid" and not camera) else [max(args.workers)]
        ds = make_dataset(path, kind, rep, camera, per_cell, args.seed)
        mb = shipped_mb(ds)
        for nw in workers:
            rate = time_loader(ds, nw, args.batch, device, args.warmup, None, build=kind != "events")
            cells.append(Cell(kind, "(events only)" if kind == "events" else rep, nw, camera, rate, mb))
            log.info("%s %s workers=%d camera=%s: %.1f samples/s", kind, rep, nw, camera, rate)
    return cells


def run_model_cells(args: argparse.Namespace, path: Path, device: torch.device) -> tuple[float, list[Cell]]:
    """Model alone on a resident batch, then fed by the baseline, worker and device loaders."""
    step = ModelStep(BINS, device)
    with Take(path) as take:
        w, h = take.sensor(SENSOR).geometry
    x = torch.randn(args.batch, BINS, h, w, device=device)
    for _ in range(3):
        step(x)
    sync(device)
    t0, k = time.perf_counter(), 0
    while k < args.batches or time.perf_counter() - t0 < 2.0:
        step(x)
        k += 1
    sync(device)
    alone = k * args.batch / (time.perf_counter() - t0)
    log.info("model alone: %.1f samples/s", alone)
    cells = []
    per_cell = (args.warmup + args.batches) * args.batch
    for kind in ("baseline", "worker", "device"):
        ds = make_dataset(path, kind, "voxel_grid", False, per_cell, args.seed)
        mb = shipped_mb(ds)
        for nw in sorted({min(4, max(args.workers)), max(args.workers)}):
            rate = time_loader(
                ds, nw, args.batch, device, args.warmup, lambda b: step(b["voxels"]), build=True
            )
            cells.append(Cell(kind, "voxel_grid", nw, False, rate, mb, with_model=True))
            log.info("%s + model, workers=%d: %.1f samples/s", kind, nw, rate)
    return alone, cells


# ----------------------------------------------------------------------------- report
def print_report(
    header: str,
    micro: list[tuple[str, float, float]],
    cells: list[Cell],
    model: tuple[float, list[Cell]] | None,
) -> None:
    print(header)
    print("\n1. one window, one thread (ms over the take's windows)")
    print(f"   {'':44s} {'median':>8s} {'best':>8s} {'median/s':>9s}")
    for name, med, best in micro:
        if best:
            print(f"   {name:44s} {med:8.2f} {best:8.2f} {1e3 / med:9.1f}")
        else:
            print(f"   {name:44s} {med:8.0f}")
    ref = {n: (med, best) for n, med, best in micro}
    for row in (NUMBA_ROW, NUMBA_OUT_ROW, GRIDDER_ROW):
        print(
            f"   speed-up of {row}: {ref[NUMPY_ROW][0] / ref[row][0]:.1f}x median, "
            f"{ref[NUMPY_ROW][1] / ref[row][1]:.1f}x best"
        )
    if not cells:
        return
    print("\n2. loader samples/s (batch on the device, representation built)")
    print(
        f"   {'representation':14s} {'built in':9s} {'frames':6s} {'MB/sample':>9s}  "
        + "  ".join(f"{'w=' + str(w):>7s}" for w in sorted({c.workers for c in cells}))
    )
    keys: dict[tuple[str, str, bool], dict[int, Cell]] = {}
    for c in cells:
        keys.setdefault((c.representation, c.path, c.camera), {})[c.workers] = c
    all_w = sorted({c.workers for c in cells})
    for (rep, kind, camera), row in keys.items():
        vals = "  ".join(f"{row[w].samples_per_s:7.1f}" if w in row else f"{'-':>7s}" for w in all_w)
        mb = next(iter(row.values())).shipped_mb
        print(f"   {rep:14s} {kind:9s} {'yes' if camera else 'no':6s} {mb:9.2f}  {vals}")
    if model is None:
        print("\n3. beside a model step: left out (no CUDA device; --model always to force)")
        return
    alone, mcells = model
    print(f"\n3. beside a SmallUNet training step (bf16 on CUDA), voxel_grid: model alone {alone:.1f}/s")
    for c in mcells:
        print(
            f"   {c.path:9s} workers={c.workers:<3d} {c.samples_per_s:7.1f} samples/s  "
            f"({100 * c.samples_per_s / alone:5.1f} % of the model alone)"
        )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--quick", action="store_true", help="short take, fewer batches and worker counts")
    ap.add_argument("--device", default="auto", help="auto (cuda when there), cpu, cuda")
    ap.add_argument("--workers", default=None, help="worker counts, comma-separated (default by cores)")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--batches", type=int, default=None, help="timed batches a cell (after the warm-up)")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=None, help="length of the recorded take")
    ap.add_argument("--take", type=Path, default=None, help="use this take (needs sensor ev0, camera cam0)")
    ap.add_argument("--take-dir", type=Path, default=None, help="record into / reuse a take from this folder")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    ap.add_argument("--no-loaders", dest="loaders", action="store_false", help="part 1 only")
    ap.add_argument(
        "--model", choices=("auto", "always", "never"), default="auto", help="model rows: auto = on CUDA only"
    )
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    cores = os.cpu_count() or 1
    if args.workers is None:
        counts = [w for w in ([0, 4, 12] if args.quick else [0, 2, 4, 8, 12]) if w <= cores]
        args.workers = counts if len(counts) > 1 or cores < 2 else [0, 2]
    else:
        args.workers = sorted({int(w) for w in str(args.workers).split(",")})
    args.batches = args.batches or (8 if args.quick else 30)
    seconds = args.seconds or (2.0 if args.quick else 5.0)
    want = args.device if args.device != "auto" else ("cuda" if torch.cuda.is_available() else "cpu")
    if want.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("--device cuda: torch sees no CUDA device")
    device = torch.device(want)
    tmp = None
    if args.take is not None:
        path = args.take
    else:
        tmp = None if args.take_dir else Path(tempfile.mkdtemp(prefix="bench-tr-"))
        path = find_or_record(args.take_dir or tmp, seconds)  # type: ignore[arg-type]
    try:
        micro = voxel_micro(path, 20 if args.quick else 100)
        cells = run_cells(args, path, device) if args.loaders else []
        with_model = args.loaders and (
            args.model == "always" or (args.model == "auto" and device.type == "cuda")
        )
        model = run_model_cells(args, path, device) if with_model else None
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    gpu = torch.cuda.get_device_name(device) if device.type == "cuda" else "none"
    load = os.getloadavg()
    header = (
        f"training reader, {time.strftime('%Y-%m-%d %H:%M')}: device {device} (GPU {gpu}), {cores} cores, "
        f"{platform.processor() or platform.machine()}, torch {torch.__version__}, load {load[0]:.2f}\n"
        f"take {path.name}: {SENSOR} 50 ms windows, {BINS}-bin voxels, batch {args.batch}, "
        f"{args.batches} timed batches a cell after {args.warmup} warm-up"
    )
    print_report(header, micro, cells, model)
    if args.json is not None:
        args.json.write_text(
            json.dumps(
                {
                    "header": header,
                    "micro": micro,
                    "cells": [asdict(c) for c in cells],
                    "model_alone": model[0] if model else None,
                    "model_cells": [asdict(c) for c in model[1]] if model else [],
                },
                indent=1,
            )
        )


if __name__ == "__main__":
    main()
