"""Compression benchmark of take files: codec vs size and throughput.

Writes the same synthetic but realistic event stream (sorted t with small deltas and
bursts, spatially clustered x/y from moving edges) and the same camera frames through
TakeWriter once per codec, then reads the events back in 50 ms windows.

    python -m bench.take_compression [--events 5000000] [--frames 60]

Reads come from the page cache, so "read" measures decompression + h5py, not the disk.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from rigd.core.devices import DeviceInfo
from rigd.core.events import EventArray
from rigd.core.frames import Frame
from rigd.core.schema import SyncReport
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.take import TakeWriter, open_take
from rigd.take.seal import finalize_take

log = logging.getLogger(__name__)

WIDTH, HEIGHT = 640, 480
FRAME_SHAPE = (1080, 1440, 3)
CODECS = ("none", "lz4", "zstd", "gzip")
PACKET = 50_000


def synth_events(n: int, seed: int = 0) -> EventArray:
    """~1.5 Mev/s mean with rate bursts; events cluster along a few moving edges."""
    rng = np.random.default_rng(seed)
    rate = 1.5e6 * (1 + 0.8 * np.sin(np.linspace(0, 20, n)))  # bursts
    dt = rng.exponential(1e6 / rate).astype(np.int64)  # mostly 0..2 us deltas
    t = 1_000_000 + np.cumsum(dt)
    k = 6
    which = rng.integers(0, k, n)
    phase = rng.uniform(0, 2 * np.pi, k)
    speed = rng.uniform(50, 300, k)  # px/s
    ts = (t - t[0]) / 1e6
    cx = (WIDTH / 2 + 250 * np.sin(phase[which] + speed[which] * ts / 200)).astype(np.float64)
    cy = rng.uniform(0, HEIGHT, k)[which] + 40 * np.cos(phase[which] + ts)
    x = np.clip(np.rint(cx + rng.normal(0, 6, n)), 0, WIDTH - 1)
    y = np.clip(np.rint(cy + rng.normal(0, 60, n)), 0, HEIGHT - 1)
    p = (rng.random(n) < np.where(np.sin(phase[which] + speed[which] * ts / 200) > 0, 0.8, 0.2)).astype(
        np.int8
    )
    return EventArray.from_arrays(x, y, p, t)


def synth_frames(n: int, seed: int = 1) -> list[NDArray[np.uint8]]:
    """Smooth scene + texture + sensor noise: neither trivially compressible nor random."""
    rng = np.random.default_rng(seed)
    h, w, _ = FRAME_SHAPE
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    texture = cv2.GaussianBlur(rng.normal(0, 40, (h, w, 3)).astype(np.float32), (0, 0), 3)
    frames = []
    for i in range(n):
        base = 110 + 60 * np.sin((xx + 8 * i) / 150)[..., None] + 30 * np.cos(yy / 90)[..., None]
        img = base + texture + rng.normal(0, 3, (h, w, 3)).astype(np.float32)
        frames.append(np.clip(img, 0, 255).astype(np.uint8))
    return frames


@dataclass
class Row:
    codec: str
    bytes_per_event: float
    write_mev_s: float
    finalize_mev_s: float
    read_mev_s: float
    frame_write_mb_s: float
    frame_ratio: float
    file_mb: float


def run_codec(codec: str, ev: EventArray, frames: list[NDArray[np.uint8]], out_dir: Path, chunk: int) -> Row:
    path = out_dir / f"bench-{codec}.h5"
    cfg = WriterConfig(event_compression=codec, frame_compression=codec, event_chunk=chunk)
    w = TakeWriter(path, rig_config_json="{}", take_id=codec, config=cfg, rigd_version="bench")
    w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="bench"), WIDTH, HEIGHT, "{}")
    w.add_camera("cam0", DeviceInfo(kind="rgb_camera", spec="bench"), FRAME_SHAPE, np.uint8, "{}")
    n = len(ev)
    t0 = time.perf_counter()
    for a in range(0, n, PACKET):
        w.append_events("ev0", ev[a : a + PACKET])
    w.flush()
    t_ev = time.perf_counter() - t0
    t0 = time.perf_counter()
    for i, img in enumerate(frames):
        w.append_frame("cam0", Frame(img, 1_000_000 + i * 33_333, 8000, i, i))
    w.flush()
    t_fr = time.perf_counter() - t0
    st = w.stats
    ev_bytes, cam_bytes = st["ev0"].stored_bytes, st["cam0"].stored_bytes
    report = SyncReport(rate_hz=30.0, n_pulses=0, t_first_pulse_us=None, t_last_pulse_us=None)
    t0 = time.perf_counter()
    finalize_take(w, {"ev0": ClockMap(0, 0, 1.00001), "cam0": ClockMap.identity()}, {}, report)
    t_fin = time.perf_counter() - t0
    w.close()
    t0 = time.perf_counter()
    got = 0
    with open_take(path) as take:
        for win in take.sensor("ev0").iter(50_000):
            got += len(win)
    t_rd = time.perf_counter() - t0
    if got != n:
        raise RuntimeError(f"{codec}: read back {got} events, wrote {n}")
    raw_frames = sum(f.nbytes for f in frames)
    return Row(
        codec,
        ev_bytes / n,
        n / t_ev / 1e6,
        n / t_fin / 1e6,
        n / t_rd / 1e6,
        raw_frames / t_fr / 1e6,
        raw_frames / max(cam_bytes, 1),
        path.stat().st_size / 1e6,
    )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--events", type=int, default=5_000_000)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--chunk", type=int, default=WriterConfig().event_chunk)
    ap.add_argument("--dir", type=Path, default=None, help="Where to write (default: a temp dir).")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    print(f"synthesising {args.events:,} events and {args.frames} frames {FRAME_SHAPE} ...", flush=True)
    ev = synth_events(args.events)
    frames = synth_frames(args.frames)
    rows: list[Row] = []
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        for codec in CODECS:
            rows.append(run_codec(codec, ev, frames, Path(tmp), args.chunk))
            print(f"  {codec} done", flush=True)
    base = rows[0]
    print(
        f"\nevents: {args.events:,} (13 B/event raw)   frames: {args.frames} x {FRAME_SHAPE}   "
        f"event chunk {args.chunk}"
    )
    hdr = (
        f"{'codec':6} {'B/event':>8} {'vs none':>8} {'write Mev/s':>12} {'finalize Mev/s':>15} "
        f"{'read Mev/s':>11} {'frame MB/s':>11} {'frame ratio':>12} {'file MB':>9}"
    )
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        print(
            f"{r.codec:6} {r.bytes_per_event:8.2f} {r.bytes_per_event / base.bytes_per_event:8.2f} "
            f"{r.write_mev_s:12.1f} {r.finalize_mev_s:15.1f} {r.read_mev_s:11.1f} "
            f"{r.frame_write_mb_s:11.0f} {r.frame_ratio:12.2f} {r.file_mb:9.1f}"
        )


if __name__ == "__main__":
    main()
