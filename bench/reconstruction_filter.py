"""Background-activity filter throughput: rigd (numba) vs dv-processing (C++, in its own process)
vs a tonic-style numpy loop, on simulated and real event streams, in the same run.

Data sets (`--data`, all three by default):

* `sim`: 640x480, 1 s of textured sprites at 300-600 px/s through the pixel model plus 2 Hz/px
  shot noise (4.9 M events).
* `gen41`: the real Prophesee Gen4.1 recording (1280x720, 25 Mev/s for 8.8 ms) from
  /work/shared/data/events, decoded by rigd and tiled end to end in time (each copy shifted by the
  recording's span) to `--real-events`.
* `gen3`: the real Gen3 recording (640x480, 10.8 Mev/s for 50 ms), tiled the same way.

dv-processing's BackgroundActivityNoiseFilter implements a different rule (any polarity,
8-neighbourhood, support 1), so its kept fraction differs; the table compares throughput on
identical input. Its timed call filters the store and hands out the kept events, so rigd's
headline row does the same (`filter()`, the kept events as arrays); `mask()`, what rigd's
reconstruct calls, is the row beside it. It runs unmodified in its own venv and process (`--peer-python`,
bench/dv_peer_worker.py), pinned to the same core as rigd; its store is built once, untimed.
The tonic-style baseline (per-event Python loop with numpy slices, as `tonic.functional.denoise`)
implements the paper's rule and must keep exactly what rigd keeps. Every filter runs in
interleaved rounds (round 0 untimed), median reported, next to the machine's limit measured in
the same rounds: memcpy GB/s of the events' 13 bytes each (x, y, p, t) and the cores. Before every
timed call the bench reads `--flush-mb` (512) MB, so no row runs in the caches the row before it
left (without it, rigd's first row ran right after dv-processing's and was the one that paid).

    python -m bench.reconstruction_filter [--data sim,gen41,gen3] [--repeats 7] [--peer-python PY]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bench.peer_process import PeerProcess
from firmware_sim.testing.sprites import SpriteScene, linear_path, simulate
from reconstruction.filters import BackgroundActivityFilter
from rigd.core.events import EventArray
from rigd.evt import read_raw

DATA_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "events"
REAL = {"gen41": "evt3_gen41_sample.raw", "gen3": "evt2_gen3_sample.raw"}
DEFAULT_PEER = Path("/tmp/scratch-perf/bin/python")
WORKER = Path(__file__).with_name("dv_peer_worker.py")
DV_DURATIONS_US = (30, 2000)
BYTES_PER_EVENT = 13  # x, y uint16; p int8; t int64
#: what dv-processing's timed call does too: filter the whole store and hand out the kept events
FILTER_ROW = "rigd BAF filter() (r=3, 30 us, >= 2): kept events"
#: what rigd's reconstruct calls: the keep mask only
MASK_ROW = "rigd BAF mask(): keep mask (what reconstruct uses)"
#: the same two with threads=2: the ON and the OFF events on the machine's first two cores
FILTER2_ROW = "rigd BAF filter(), threads=2 (ON | OFF on 2 cores)"
MASK2_ROW = "rigd BAF mask(), threads=2 (ON | OFF on 2 cores)"


def tonic_style(
    ev: EventArray, width: int, height: int, radius: int = 3, window: int = 30, support: int = 2
) -> NDArray[np.bool_]:
    """Per-event Python loop over a padded timestamp memory, numpy slice per event (tonic's approach)."""
    mem = np.full((2, height + 2 * radius, width + 2 * radius), -(10**15), np.int64)
    keep = np.zeros(len(ev), bool)
    xs, ys, ps, ts = ev.x.astype(np.int64), ev.y.astype(np.int64), (ev.p > 0).astype(np.int64), ev.t
    for i in range(len(ev)):
        x, y, p, t = xs[i], ys[i], ps[i], ts[i]
        win = mem[p, y : y + 2 * radius + 1, x : x + 2 * radius + 1]
        n = int(np.count_nonzero(win >= t - window)) - int(mem[p, y + radius, x + radius] >= t - window)
        keep[i] = n >= support
        mem[p, y + radius, x + radius] = t
    return keep


def make_sim(seconds: float, noise_hz: float) -> EventArray:
    paths = [
        linear_path(20, 60, 300, 40),
        linear_path(600, 200, -450, 0),
        linear_path(100, 400, 400, -150),
        linear_path(300, 20, 100, 600),
    ]
    scene = SpriteScene(640, 480, paths, sprite_px=64, seed=3)
    return simulate(scene, 0.0, seconds, threshold=0.15, shot_noise_rate_hz=noise_hz, max_px_per_step=0.7)


def tile_in_time(ev: EventArray, n_events: int) -> EventArray:
    """The recording repeated end to end until it holds at least n_events, each copy shifted by its
    span + 1 us (the bytes' events unchanged: same pixels, polarities and time differences)."""
    copies = max(1, -(-n_events // len(ev)))
    span = int(ev.t[-1] - ev.t[0]) + 1
    shift = np.repeat(np.arange(copies, dtype=np.int64) * span, len(ev))
    return EventArray(
        np.tile(ev.x, copies), np.tile(ev.y, copies), np.tile(ev.p, copies), np.tile(ev.t, copies) + shift
    )


def load(name: str, args: argparse.Namespace) -> tuple[str, EventArray, int, int]:
    """(description, events, width, height) of one data set."""
    if name == "sim":
        ev = make_sim(args.seconds, args.noise_hz)
        return f"sim 640x480, {args.seconds:g} s sprites + {args.noise_hz:g} Hz/px noise", ev, 640, 480
    path = DATA_DIR / REAL[name]
    hdr, dec = read_raw(path)
    ev = dec.events
    rate = len(ev) / max(1, int(ev.t[-1] - ev.t[0])) if len(ev) else 0.0
    desc = (
        f"{path.name} {hdr.width}x{hdr.height} (real, {len(ev)} events at {rate:.1f} Mev/s), "
        f"tiled x{-(-args.real_events // len(ev))} in time"
    )
    return desc, tile_in_time(ev, args.real_events), int(hdr.width), int(hdr.height)


class DvPeer(PeerProcess):
    """dv-processing's filter in its own venv and process (bench/dv_peer_worker.py)."""

    def __init__(self, python: Path, events: Path, width: int, height: int, cpu: int | None) -> None:
        super().__init__([str(python), str(WORKER), str(events), str(width), str(height)], cpu=cpu)

    def filter(self, duration_us: int) -> tuple[float, float]:
        """(seconds, kept fraction) of one run over the whole store."""
        assert self.proc.stdin is not None
        assert self.proc.stdout is not None
        self.proc.stdin.write(f"{duration_us}\n")
        self.proc.stdin.flush()
        answer = json.loads(self.proc.stdout.readline())
        return float(answer["seconds"]), int(answer["kept"]) / max(1, int(answer["events"]))


def uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "load average: {:.2f}, {:.2f}, {:.2f}".format(*os.getloadavg())


def on_cores(cores: set[int] | None, fn: Callable[[], float]) -> Callable[[], float]:
    """`fn` run with this thread (and the threads it starts) allowed on `cores`, then back."""
    if cores is None:
        return fn

    def run() -> float:
        pinned = os.sched_getaffinity(0)
        os.sched_setaffinity(0, cores)
        try:
            return fn()
        finally:
            os.sched_setaffinity(0, pinned)

    return run


def bench_one(name: str, args: argparse.Namespace, cpu: int | None, two: set[int] | None) -> dict[str, float]:
    """Print one data set's table; returns Mev/s per row name."""
    t0 = time.perf_counter()
    desc, ev, w, h = load(name, args)
    n = len(ev)
    print(f"\n## {name}: {desc}: {n / 1e6:.2f} M events (ready in {time.perf_counter() - t0:.1f} s)")

    # name -> a call returning the kept fraction; timed round-robin so load hits all alike
    timed: dict[str, Callable[[], float]] = {}
    timed[FILTER_ROW] = lambda: len(BackgroundActivityFilter(w, h).filter(ev)) / n
    timed[MASK_ROW] = lambda: np.count_nonzero(BackgroundActivityFilter(w, h).mask(ev)) / n
    if two is not None:
        timed[FILTER2_ROW] = on_cores(
            two, lambda: len(BackgroundActivityFilter(w, h, threads=2).filter(ev)) / n
        )
        timed[MASK2_ROW] = on_cores(
            two, lambda: np.count_nonzero(BackgroundActivityFilter(w, h, threads=2).mask(ev)) / n
        )

    def chunked() -> float:
        baf = BackgroundActivityFilter(w, h)
        return sum(len(baf.filter(ev[a : a + 100_000])) for a in range(0, n, 100_000)) / n

    timed["rigd BAF filter(), 100k-event chunks"] = chunked
    src: list[NDArray[Any]] = [ev.x, ev.y, ev.p, ev.t]
    dst = [np.empty_like(a) for a in src]

    def memcpy() -> float:
        for s, d in zip(src, dst, strict=True):
            np.copyto(d, s)
        return float("nan")

    timed[f"memcpy of the events ({BYTES_PER_EVENT} B each), machine limit"] = memcpy
    peer: DvPeer | None = None
    # rows the peer times itself (in its process): name -> (worker, duration us)
    peer_rows: dict[str, tuple[DvPeer, int]] = {}
    tmp = tempfile.TemporaryDirectory()
    if args.peer_python.exists():
        npz = Path(tmp.name) / "events.npz"
        np.savez(npz, x=ev.x, y=ev.y, p=ev.p, t=ev.t)
        peer = DvPeer(args.peer_python, npz, w, h, cpu)
        print(
            f"{peer.hello['peer']} in its own process; store built in {peer.hello['store_s']:.1f} s (untimed)"
        )
        if peer.hello["events"] != n:
            raise SystemExit(f"dv worker holds {peer.hello['events']} events, not {n}")
        for d_us in DV_DURATIONS_US:
            peer_rows[f"dv-processing BackgroundActivityNoiseFilter ({d_us} us)"] = (peer, d_us)
    else:
        print(f"dv-processing: {args.peer_python} not found (a venv with `pip install dv-processing`)")

    rows = [*timed, *peer_rows]
    times: dict[str, list[float]] = {k: [] for k in rows}
    kept_of: dict[str, float] = {}
    flush = np.ones(args.flush_mb * 2**20 // 8) if args.flush_mb else None
    for rnd in range(args.repeats + 1):  # round 0 warms up (JIT, caches), not timed
        for row in rows:
            if flush is not None:  # every row starts from the same cold caches, the peer's too
                flush.sum()
            if row in peer_rows:
                worker, d_us = peer_rows[row]
                sec, kept_of[row] = worker.filter(d_us)
            else:
                t_start = time.perf_counter()
                kept_of[row] = timed[row]()
                sec = time.perf_counter() - t_start
            if rnd:
                times[row].append(sec)
    if peer is not None:
        peer.close()
    tmp.cleanup()

    m = min(args.tonic_events, n)
    sub = ev[:m]
    t_start = time.perf_counter()
    keep_tonic = tonic_style(sub, w, h)
    dt_tonic = time.perf_counter() - t_start
    same = bool(np.array_equal(keep_tonic, BackgroundActivityFilter(w, h).mask(sub)))
    # threads=2 on the whole set: the same kept events as one thread
    same_split = two is None or bool(
        np.array_equal(
            BackgroundActivityFilter(w, h).mask(ev), BackgroundActivityFilter(w, h, threads=2).mask(ev)
        )
    )

    print(f"\n| {'filter':58s} | {'time s':>8s} | {'Mev/s':>7s} | {'GB/s':>6s} | {'kept':>6s} |")
    print(f"|{'-' * 60}|{'-' * 10}|{'-' * 9}|{'-' * 8}|{'-' * 8}|")
    mev: dict[str, float] = {}
    for row in rows:
        sec = float(np.median(times[row]))
        mev[row] = n / sec / 1e6
        kept = "" if np.isnan(kept_of[row]) else f"{kept_of[row]:6.1%}"
        gbs = n * BYTES_PER_EVENT / sec / 1e9
        print(f"| {row:58s} | {sec:8.4f} | {mev[row]:7.1f} | {gbs:6.2f} | {kept:>6s} |")
    tonic_row = f"tonic-style numpy loop (first {m} events, 1 run)"
    tonic_mev = m / dt_tonic / 1e6
    print(f"| {tonic_row:58s} | {dt_tonic:8.4f} | {tonic_mev:7.1f} | {'':6s} | {keep_tonic.mean():6.1%} |")
    for row in peer_rows:
        filt, mask = mev[FILTER_ROW] / mev[row], mev[MASK_ROW] / mev[row]
        line = f"vs {row}: rigd filter() {filt:.2f}x, rigd mask() {mask:.2f}x"
        if two is not None:
            f2, m2 = mev[FILTER2_ROW] / mev[row], mev[MASK2_ROW] / mev[row]
            line += f"; threads=2: filter() {f2:.2f}x, mask() {m2:.2f}x"
        print(line)
    print(f"tonic-style keeps exactly what rigd keeps: {same}")
    if two is not None:
        print(f"threads=2 keeps exactly what one thread keeps: {same_split}")
    if not same:
        raise SystemExit(f"{name}: rigd's kept set differs from the tonic-style reference")
    if not same_split:
        raise SystemExit(f"{name}: threads=2 kept other events than one thread")
    return mev


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="sim,gen41,gen3", help="comma-separated: sim, gen41, gen3")
    ap.add_argument("--seconds", type=float, default=1.0, help="sim: seconds of sprites")
    ap.add_argument("--noise-hz", type=float, default=2.0, help="sim: shot noise per pixel")
    ap.add_argument("--real-events", type=int, default=4_800_000, help="real recordings: tile to this many")
    ap.add_argument("--tonic-events", type=int, default=200_000, help="events given to the slow baseline")
    ap.add_argument("--repeats", type=int, default=7, help="timed rounds (median reported)")
    ap.add_argument(
        "--flush-mb",
        type=int,
        default=512,
        help="read this many MB before every timed call, so each starts from cold caches whatever ran "
        "before it (0: off, each row then inherits the previous row's caches)",
    )
    ap.add_argument(
        "--peer-python",
        type=Path,
        default=Path(os.environ.get("RIGD_BENCH_PEER_PYTHON", str(DEFAULT_PEER))),
        help="python of a venv with dv-processing installed (its own process)",
    )
    args = ap.parse_args()
    names = [s.strip() for s in args.data.split(",") if s.strip()]
    for nm in names:
        if nm != "sim" and nm not in REAL:
            raise SystemExit(f"--data: unknown data set {nm!r} (sim, {', '.join(REAL)})")
    cpu = None
    two: set[int] | None = None
    if hasattr(os, "sched_setaffinity"):  # one core for every filter, the peer's process included
        cores = sorted(os.sched_getaffinity(0))
        cpu = cores[0]
        two = set(cores[:2]) if len(cores) >= 2 else None
        os.sched_setaffinity(0, {cpu})
    print(
        f"machine: {os.cpu_count()} cores, every filter pinned to cpu {cpu} except the threads=2 rows "
        f"(cpus {sorted(two) if two else '-'}); python {sys.version.split()[0]}"
    )
    print(f"uptime at start: {uptime()}")
    flushed = f"{args.flush_mb} MB read before every timed call" if args.flush_mb else "not flushed"
    print(f"caches: {flushed}")
    summary = []
    for nm in names:
        mev = bench_one(nm, args, cpu, two)
        dv30 = mev.get(f"dv-processing BackgroundActivityNoiseFilter ({DV_DURATIONS_US[0]} us)")
        mem = next(v for k, v in mev.items() if k.startswith("memcpy"))
        summary.append((nm, mev[FILTER_ROW], mev[MASK_ROW], mev.get(FILTER2_ROW), dv30, mem))
    print(f"\nuptime at the end: {uptime()}")
    print(f"median of {args.repeats} interleaved rounds each\n")
    print(
        "| data | rigd filter() Mev/s | rigd mask() Mev/s | filter() threads=2 Mev/s | dv-processing 30 us "
        "Mev/s | filter() / dv | mask() / dv | filter() threads=2 / dv | memcpy of the events GB/s (limit) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for nm, filt, mask, filt2, dv30, mem in summary:
        f2 = f"{filt2:.1f}" if filt2 else "-"
        ratios = f"{filt / dv30:.2f}x | {mask / dv30:.2f}x" if dv30 else "- | -"
        ratios += f" | {filt2 / dv30:.2f}x" if dv30 and filt2 else " | -"
        dv = f"{dv30:.1f}" if dv30 else "-"
        print(
            f"| {nm} | {filt:.1f} | {mask:.1f} | {f2} | {dv} | {ratios} | {mem * BYTES_PER_EVENT / 1e3:.2f} |"
        )


if __name__ == "__main__":
    main()
