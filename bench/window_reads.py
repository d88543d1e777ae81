"""Random 50 ms event windows: rigd's reader on a default take against DSEC's EventSlicer on its
DSEC export, same windows, same run.

    python -m bench.window_reads [--take TAKE.h5] [--export DIR] [--windows 500] [--sensor ev0]
        [--peer-python /tmp/scratch-window/bin/python] [--dsec-repo DIR] [--cpu N] [--what-if]

Without `--take` it captures one with `rigd capture --duration 5 --sim-clock virtual --local`
(the README's default sim rig: events stored as the EVT words the sensor sent); without
`--export` it runs `rigd export TAKE --format dsec`. rigd reads with `take.sensor(name).events(t0,
t1)` in this process; DSEC's `EventSlicer.get_events` runs, unmodified, in its own venv and
process (`bench/dsec_slicer_worker.py`; `--dsec-repo` a checkout of uzh-rpg/DSEC, else the
commit `bench.consumers` pins, fetched once under --work, or from `RIGD_GIT_MIRROR`). The two are
interleaved window by window (alternating which goes first), so background load hits both
alike; each answers a digest of the events it returned (x, y, p, t) and every window must be
identical. Both files were just written or read, so the windows come from the page cache; the
table gives the disk's read rate (O_DIRECT) and memcpy beside them, and the load average.
`--what-if` adds rows for copies of the take whose words are stored again with 64 KiB Zstd
chunks and without compression: what the writer's storage settings cost a window.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import logging
import mmap
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import h5py
import hdf5plugin
import numpy as np
from numpy.typing import NDArray

from bench.peer_process import PeerProcess
from rigd.core.events import EventArray
from rigd.take import open_take
from rigd.take.event_series import EventSeries

log = logging.getLogger(__name__)

DEFAULT_PEER = Path("/tmp/scratch-window/bin/python")
WORKER = Path(__file__).resolve().parent / "dsec_slicer_worker.py"
#: Untimed windows each reader answers first (numba compiles EventSlicer's search on its first call).
WARMUP = 5


def digest(ev: EventArray, origin: int) -> str:
    """What the worker hashes: x, y uint16, p as DSEC's 0/1 uint8, t int64 in the export's us."""
    h = hashlib.sha1()
    for a, dt in ((ev.x, np.uint16), (ev.y, np.uint16), ((ev.p > 0), np.uint8), (ev.t - origin, np.int64)):
        h.update(np.ascontiguousarray(a, dtype=dt).tobytes())
    return h.hexdigest()


def cli(*args: str) -> None:
    """Run a rigd command with this interpreter; its output tail in the error when it fails."""
    cmd = [sys.executable, "-m", "rigd.app.cli", *args]
    p = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if p.returncode != 0:
        tail = (p.stdout + p.stderr)[-3000:]
        raise RuntimeError(f"{' '.join(cmd[2:6])} ... exited {p.returncode}:\n{tail}")


def make_take(work: Path, seconds: float) -> Path:
    out = work / "takes"
    cli("capture", "--duration", f"{seconds:g}", "--sim-clock", "virtual", "--local", "--out", str(out))
    takes = sorted(out.glob("*.h5"), key=lambda p: p.stat().st_mtime)
    if not takes:
        raise RuntimeError(f"rigd capture wrote no take into {out}")
    return takes[-1]


def disk_read_mb_s(path: Path, limit: int = 256 << 20) -> float:
    """Sequential read rate of `path` bypassing the page cache (O_DIRECT, 4 MiB reads)."""
    block = 4 << 20
    buf = mmap.mmap(-1, block)  # page-aligned, as O_DIRECT wants
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECT", 0))
    try:
        t0, done = time.perf_counter(), 0
        while done < limit:
            k = os.readv(fd, [buf])
            if k <= 0:
                break
            done += k
        return done / (time.perf_counter() - t0) / 1e6
    finally:
        os.close(fd)
        buf.close()


def memcpy_gb_s(nbytes: int = 256 << 20) -> float:
    src = np.ones(nbytes, np.uint8)
    dst = np.empty_like(src)
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        np.copyto(dst, src)
        best = min(best, time.perf_counter() - t0)
    return nbytes / best / 1e9


#: `--what-if`: the take's EVT words stored again with another chunk size / codec (chunk bytes,
#: codec): what the writer's settings would change for window reads (index, rows, all else kept).
WHAT_IF = {"zstd, 64 KiB chunks": (1 << 16, "zstd"), "uncompressed, 256 KiB chunks": (1 << 18, "none")}


def restore_words(take: Path, sensor: str, dest: Path, chunk: int, codec: str) -> Path:
    """A copy of the take whose sensor's `evt_words` dataset is written again with `chunk`
    bytes per chunk and `codec` (zstd level 1 as the writer uses, or none)."""
    shutil.copyfile(take, dest)
    with h5py.File(dest, "r+") as f:
        g = f[f"events/{sensor}"]
        old = g["evt_words"]
        data, attrs = old[()], dict(old.attrs)
        del g["evt_words"]
        kw = dict(hdf5plugin.Zstd(clevel=1)) if codec == "zstd" else {}
        new = g.create_dataset("evt_words", data=data, chunks=(chunk,), maxshape=(None,), **kw)
        new.attrs.update(attrs)
    return dest


class Reader(Protocol):
    def read(self, a: int, b: int) -> tuple[float, float, int, str]:
        """(wall s, CPU s, events, digest) of the window [a, b) in rig us."""
        ...


@dataclass
class Ours:
    series: EventSeries
    origin: int

    def read(self, a: int, b: int) -> tuple[float, float, int, str]:
        t0, c0 = time.perf_counter(), time.thread_time()
        ev = self.series.events(a, b)
        dt, dc = time.perf_counter() - t0, time.thread_time() - c0
        return dt, dc, len(ev), digest(ev, self.origin)


@dataclass
class Peer:
    peer: PeerProcess
    origin: int

    def read(self, a: int, b: int) -> tuple[float, float, int, str]:
        got = self.peer.ask(f"{a - self.origin} {b - self.origin}")
        if got["events"] < 0:
            raise RuntimeError(f"EventSlicer returned None for [{a - self.origin}, {b - self.origin})")
        return float(got["seconds"]), float(got["cpu"]), int(got["events"]), str(got["digest"])


@dataclass
class Column:
    name: str
    ms: NDArray[np.float64]
    cpu_ms: NDArray[np.float64]
    events: NDArray[np.int64]

    def row(self) -> str:
        med, p99 = np.median(self.ms), np.percentile(self.ms, 99)
        c_med, c_p99 = np.median(self.cpu_ms), np.percentile(self.cpu_ms, 99)
        n = float(np.mean(self.events))
        return (
            f"| {self.name} | {med:.3f} | {p99:.3f} | {c_med:.3f} | {c_p99:.3f} | {n:,.0f} "
            f"| {n / med / 1e3:.1f} | {n / c_med / 1e3:.1f} |"
        )


def ms(seconds: list[float]) -> NDArray[np.float64]:
    return np.asarray(seconds, np.float64) * 1e3


def dsec_repo(args: argparse.Namespace) -> Path:
    if args.dsec_repo is not None:
        return Path(args.dsec_repo)
    from bench.consumers import checkout

    return checkout(args.work, "dsec")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--take", type=Path, default=None, help="A finalized take (default: capture one).")
    ap.add_argument("--export", type=Path, default=None, help="Its DSEC export (default: export it).")
    ap.add_argument("--work", type=Path, default=Path("/tmp/rigd-window-reads"))
    ap.add_argument("--seconds", type=float, default=5.0, help="Length of the take captured.")
    ap.add_argument("--sensor", default="ev0")
    ap.add_argument("--windows", type=int, default=500)
    ap.add_argument("--window-ms", type=float, default=50.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--peer-python", type=Path, default=DEFAULT_PEER)
    ap.add_argument("--dsec-repo", type=Path, default=None)
    ap.add_argument("--cpu", type=int, default=None, help="Pin both readers to this CPU.")
    ap.add_argument(
        "--what-if",
        action="store_true",
        help="Also read copies of the take with its words re-stored (zstd 64 KiB chunks; uncompressed).",
    )
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    args.work.mkdir(parents=True, exist_ok=True)
    take = args.take or make_take(args.work, args.seconds)
    export = args.export
    if export is None:
        export = args.work / "dsec"
        cli("export", str(take), "--format", "dsec", "--out", str(export), "--force")
    events_h5 = export / "events" / args.sensor / "events.h5"
    origin = int(json.loads((export / "split.json").read_text())["rig_time_origin_us"])
    if args.cpu is not None:
        os.sched_setaffinity(0, {args.cpu})
    if not args.peer_python.exists():
        raise SystemExit(f"{args.peer_python}: no such python (a venv with h5py, hdf5plugin, numba, numpy)")
    argv_peer = [str(args.peer_python), str(WORKER), str(dsec_repo(args)), str(events_h5)]
    peer = PeerProcess(argv_peer + ([str(args.cpu)] if args.cpu is not None else []))
    w_us = int(args.window_ms * 1000)
    what_ifs = {
        name: restore_words(take, args.sensor, args.work / f"what-if-{codec}-{chunk}.h5", chunk, codec)
        for name, (chunk, codec) in (WHAT_IF.items() if args.what_if else ())
    }
    with contextlib.ExitStack() as stack:
        stack.callback(peer.close)
        series = stack.enter_context(open_take(take)).sensor(args.sensor)
        storage = series.storage
        readers: dict[str, Reader] = {"rigd `Take.sensor().events` (EVT words take)": Ours(series, origin)}
        for name, path in what_ifs.items():
            readers[f"rigd, words re-stored: {name} (what-if)"] = Ours(
                stack.enter_context(open_take(path)).sensor(args.sensor), origin
            )
        readers["DSEC `EventSlicer.get_events` (DSEC export)"] = Peer(peer, origin)
        # inside the export's events and its ms index (EventSlicer answers None past it)
        h = peer.hello
        lo = origin + int(h["t_offset"]) + 1000
        hi = origin + min(int(h["t_final"]), (int(h["ms_to_idx"]) - 2) * 1000) - w_us
        if hi <= lo:
            raise RuntimeError(f"{events_h5}: shorter than one {args.window_ms:g} ms window")
        starts = np.random.default_rng(args.seed).integers(lo, hi, args.windows + WARMUP)
        timed: dict[str, list[tuple[float, float, int]]] = {name: [] for name in readers}
        mismatched: list[str] = []
        names = list(readers)
        for i, s in enumerate(starts.tolist()):
            a, b = int(s), int(s) + w_us
            answers = {}
            for k in range(len(names)):  # each window in a rotated order
                name = names[(i + k) % len(names)]
                answers[name] = readers[name].read(a, b)
                if i >= WARMUP:
                    timed[name].append(answers[name][:3])
            if len({d for *_, d in answers.values()}) != 1:
                counts = ", ".join(f"{n}: {ans[2]}" for n, ans in answers.items())
                mismatched.append(f"[{a}, {b}) rig us: {counts}")
    load = os.getloadavg()
    uptime = subprocess.run(["uptime"], capture_output=True, text=True, check=False).stdout.strip()
    disk = disk_read_mb_s(take)
    mem = memcpy_gb_s()
    cols = [
        Column(name, ms([t[0] for t in v]), ms([t[1] for t in v]), np.asarray([t[2] for t in v]))
        for name, v in timed.items()
    ]
    print(f"take {take} ({args.sensor} stored as {storage}), export {events_h5}")
    print(f"peer: {peer.hello['peer']}; {peer.hello['versions']}")
    print(
        f"{args.windows} random {args.window_ms:g} ms windows of {args.sensor} (seed {args.seed}), "
        "interleaved; "
        f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; disk read {disk:.0f} MB/s (O_DIRECT), "
        f"memcpy {mem:.1f} GB/s"
    )
    print(f"uptime: {uptime}")
    print(
        "| reader | median ms | p99 ms | CPU median ms | CPU p99 ms | events/window | Mev/s (median) "
        "| Mev/s (CPU median) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for c in cols:
        print(c.row())
    for what, mine, peers in (("wall", cols[0].ms, cols[-1].ms), ("CPU", cols[0].cpu_ms, cols[-1].cpu_ms)):
        r_med = np.median(peers) / np.median(mine)
        r_p99 = np.percentile(peers, 99) / np.percentile(mine, 99)
        print(
            f"rigd vs EventSlicer, {what}: {r_med:.2f}x median, {r_p99:.2f}x p99 "
            "(EventSlicer time / rigd time)"
        )
    same = args.windows + WARMUP - len(mismatched)
    print(f"identical windows: {same} of {args.windows + WARMUP} (count and x/y/p/t, every reader)")
    if mismatched:
        for line in mismatched[:5]:
            print(f"  differs: {line}")
        raise SystemExit(1)


if __name__ == "__main__":
    main()
