"""Capture throughput on the simulated rig, side by side with a raw sequential write.

    python -m bench.capture_throughput [--duration 5] [--format rgb8|mono8|bayer_rg8] [--out DIR]
                                       [--fsync/--no-fsync] [--flush-interval S]

Prints sustained frames/s, events/s and MB/s written by `rigd capture`, and the MB/s of
writing the same number of bytes with plain sequential writes (+ fsync) to the same
directory in the same run, so the pipeline's overhead over the disk is visible.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
import uuid
from pathlib import Path

from rigd.app.capture import run_capture
from rigd.app.config import default_sim_rig

_BLOCK = 4 << 20


def raw_write(path: Path, n_bytes: int) -> float:
    """Seconds to write n_bytes sequentially in 4 MiB blocks and fsync."""
    block = os.urandom(_BLOCK)
    t0 = time.perf_counter()
    with open(path, "wb", buffering=0) as f:
        left = n_bytes
        while left > 0:
            f.write(block[: min(left, _BLOCK)])
            left -= _BLOCK
        os.fsync(f.fileno())
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=5.0)
    ap.add_argument("--format", choices=["rgb8", "mono8", "bayer_rg8"], default="rgb8")
    ap.add_argument("--rate", type=float, default=30.0, help="trigger rate, Hz (stress: raise it)")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--frame-compression", choices=["none", "lz4", "zstd", "gzip"], default=None)
    ap.add_argument("--event-compression", choices=["none", "lz4", "zstd", "gzip"], default=None)
    ap.add_argument("--out", type=Path, default=None, help="directory on the disk to measure (default: tmp)")
    ap.add_argument(
        "--fsync", action=argparse.BooleanOptionalAction, default=True, help="writer.fsync (durable flushes)"
    )
    ap.add_argument("--flush-interval", type=float, default=None, help="writer.flush_interval_s")
    args = ap.parse_args()

    out_dir = Path(tempfile.mkdtemp(prefix="rigd-bench-", dir=args.out))
    try:
        cfg = default_sim_rig(
            world=f"bench-{uuid.uuid4().hex[:8]}",
            pixel_format=args.format,
            resolution=(args.width, args.height),
            rate_hz=args.rate,
        )
        if args.frame_compression:
            cfg.writer.frame_compression = args.frame_compression
        if args.event_compression:
            cfg.writer.event_compression = args.event_compression
        cfg.writer.fsync = args.fsync
        if args.flush_interval:
            cfg.writer.flush_interval_s = args.flush_interval
        res = run_capture(cfg, out_dir, args.duration)
        n_frames = sum(res.frames.values())
        n_events = sum(res.events.values())
        size = res.bytes_written
        raw_s = raw_write(out_dir / "raw.bin", size)
        losses = sum(loss.count for loss in res.report.losses)
        cap = res.capture_s
        rows = [
            ("rigd capture (sim rig)", cap, n_frames / cap, n_events / cap, size / cap),
            ("raw sequential write", raw_s, float("nan"), float("nan"), size / raw_s),
        ]
        print(
            f"capture: {args.duration:.1f} s of pulses at {args.rate:g} Hz, "
            f"{len(res.frames)} cameras {args.width}x{args.height} {args.format}, "
            f"{len(res.events)} event sensors, frame compression {cfg.writer.frame_compression}, "
            f"event compression {cfg.writer.event_compression}"
        )
        print("(capture: START to last byte written, incl. the drain after the last pulse)")
        print(f"{'pipeline':<26}{'time s':>9}{'frames/s':>11}{'events/s':>13}{'MB/s':>10}")
        for name, wall, fps, eps, bps in rows:
            print(f"{name:<26}{wall:>9.2f}{fps:>11.1f}{eps:>13,.0f}{bps / 1e6:>10.1f}")
        print(f"take size {size / 1e6:.1f} MB; frames {res.frames}; losses recorded: {losses}")
        print(
            f"flushes every {cfg.writer.flush_interval_s:g} s, fsync {'on' if args.fsync else 'off'}: "
            f"{res.flushes} flushes, longest {res.flush_max_s * 1e3:.0f} ms"
        )
        print(f"whole run incl. device open and finalize: {res.wall_s:.2f} s")
        worst = max((d.residual_rms_us for d in res.report.devices.values()), default=float("nan"))
        print(f"worst per-device sync residual RMS: {worst:.2f} us")
    finally:
        shutil.rmtree(out_dir, ignore_errors=True)


if __name__ == "__main__":
    main()
