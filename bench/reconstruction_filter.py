"""Background-activity filter throughput: rigd (numba) vs dv-processing (C++) vs a tonic-style numpy loop.

Same events for every filter, same run: a 640x480 simulated sequence (textured sprites at 300-600 px/s
through the pixel model) plus shot noise. dv-processing's BackgroundActivityNoiseFilter implements a
different rule (any polarity, 8-neighbourhood, support 1), so its kept fraction differs; the table
compares throughput on identical input. The tonic-style baseline (per-event Python loop with numpy
slices, as `tonic.functional.denoise`) implements the paper's rule and must keep exactly what rigd keeps.
Every filter runs on the same one core, in interleaved rounds (round 0 untimed), median reported.

    python -m bench.reconstruction_filter [--seconds 1.0] [--noise-hz 2.0] [--peer-site DIR]

dv-processing runs its own code from its own venv: `--peer-site` (default
/tmp/scratch-perf/lib/python3.11/site-packages where it exists) is appended to the module path
after the project's, so only what the project lacks (dv_processing) comes from there.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from firmware_sim.testing.sprites import SpriteScene, linear_path, simulate
from reconstruction.filters import BackgroundActivityFilter
from rigd.core.events import EventArray

W, H = 640, 480


def tonic_style(ev: EventArray, radius: int = 3, window: int = 30, support: int = 2) -> NDArray[np.bool_]:
    """Per-event Python loop over a padded timestamp memory, numpy slice per event (tonic's approach)."""
    mem = np.full((2, H + 2 * radius, W + 2 * radius), -(10**15), np.int64)
    keep = np.zeros(len(ev), bool)
    xs, ys, ps, ts = ev.x.astype(np.int64), ev.y.astype(np.int64), (ev.p > 0).astype(np.int64), ev.t
    for i in range(len(ev)):
        x, y, p, t = xs[i], ys[i], ps[i], ts[i]
        win = mem[p, y : y + 2 * radius + 1, x : x + 2 * radius + 1]
        n = int(np.count_nonzero(win >= t - window)) - int(mem[p, y + radius, x + radius] >= t - window)
        keep[i] = n >= support
        mem[p, y + radius, x + radius] = t
    return keep


def make_events(seconds: float, noise_hz: float) -> EventArray:
    paths = [
        linear_path(20, 60, 300, 40),
        linear_path(600, 200, -450, 0),
        linear_path(100, 400, 400, -150),
        linear_path(300, 20, 100, 600),
    ]
    scene = SpriteScene(W, H, paths, sprite_px=64, seed=3)
    return simulate(scene, 0.0, seconds, threshold=0.15, shot_noise_rate_hz=noise_hz, max_px_per_step=0.7)


def median_time(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time of `repeats` calls (the machine is shared: medians, not best-of)."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--noise-hz", type=float, default=2.0)
    ap.add_argument("--tonic-events", type=int, default=200_000, help="events given to the slow baseline")
    ap.add_argument("--repeats", type=int, default=7, help="timed runs per filter (median reported)")
    ap.add_argument(
        "--peer-site",
        default="/tmp/scratch-perf/lib/python3.11/site-packages",
        help="site-packages of a venv with dv-processing (appended to the module path)",
    )
    args = ap.parse_args()
    if hasattr(os, "sched_setaffinity"):  # one core for every filter
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    if os.path.isdir(args.peer_site) and args.peer_site not in sys.path:
        sys.path.append(args.peer_site)
    load1, load5, _ = os.getloadavg()
    print(f"load: {load1:.2f} {load5:.2f} (1, 5 min averages) at start")

    t0 = time.perf_counter()
    ev = make_events(args.seconds, args.noise_hz)
    n = len(ev)
    print(f"events: {n} ({n / 1e6:.2f} M) at {W}x{H}, made in {time.perf_counter() - t0:.1f} s")

    rows: list[tuple[str, int, float, float]] = []
    # name -> (the call, which returns the kept fraction); timed round-robin, so background load
    # on the shared machine hits every filter alike
    timed: dict[str, Callable[[], float]] = {}
    keep_holder: list[NDArray[np.bool_]] = []

    def run_rigd() -> float:
        keep_holder[:] = [BackgroundActivityFilter(W, H).mask(ev)]
        return float(keep_holder[0].mean())

    def run_chunked() -> float:
        baf = BackgroundActivityFilter(W, H)
        kept = sum(int(np.count_nonzero(baf.mask(ev[a : a + 100_000]))) for a in range(0, n, 100_000))
        return kept / n

    timed["rigd BAF (numba, 1 core, r=3 Chebyshev, 30 us, >=2)"] = run_rigd
    timed["rigd BAF, 1 core, 100k-event chunks"] = run_chunked
    try:
        import dv_processing as dv
    except ImportError:
        print("dv-processing: not installed (pip install dv-processing)")
    else:
        from datetime import timedelta

        t_conv = time.perf_counter()
        store = dv.EventStore()
        for t, x, y, p in zip(ev.t.tolist(), ev.x.tolist(), ev.y.tolist(), (ev.p > 0).tolist(), strict=True):
            store.push_back(t, x, y, p)
        print(f"dv EventStore built in {time.perf_counter() - t_conv:.1f} s (not timed)")
        for dur_us in (30, 2000):

            def run_dv(d: int = dur_us) -> float:
                f = dv.noise.BackgroundActivityNoiseFilter(
                    (W, H), backgroundActivityDuration=timedelta(microseconds=d)
                )
                f.accept(store)
                return float(f.generateEvents().size() / n)

            timed[f"dv-processing BackgroundActivityNoiseFilter ({dur_us} us)"] = run_dv
    times: dict[str, list[float]] = {k: [] for k in timed}
    kept_of: dict[str, float] = {}
    for rnd in range(args.repeats + 1):  # round 0 warms up (JIT, caches), not timed
        for name, fn in timed.items():
            t0 = time.perf_counter()
            kept_of[name] = fn()
            if rnd:
                times[name].append(time.perf_counter() - t0)
    for name in timed:
        rows.append((name, n, float(np.median(times[name])), kept_of[name]))

    m = min(args.tonic_events, n)
    sub = ev[:m]
    keep_tonic: list[NDArray[np.bool_]] = []
    dt_t = median_time(lambda: keep_tonic.append(tonic_style(sub)), 1)
    same = bool(np.array_equal(keep_tonic[0], BackgroundActivityFilter(W, H).mask(sub)))
    rows.append((f"tonic-style numpy loop (first {m} events)", m, dt_t, float(keep_tonic[0].mean())))

    print()
    print(f"| {'filter':58s} | {'events':>9s} | {'time s':>8s} | {'Mev/s':>7s} | {'kept':>6s} |")
    print(f"|{'-' * 60}|{'-' * 11}|{'-' * 10}|{'-' * 9}|{'-' * 8}|")
    for name, cnt, sec, kept in rows:
        print(f"| {name:58s} | {cnt:9d} | {sec:8.4f} | {cnt / sec / 1e6:7.1f} | {kept:6.1%} |")
    load_end = os.getloadavg()[0]
    print(
        f"\nmedian of {args.repeats} interleaved rounds (tonic-style: 1 run); load at the end {load_end:.2f}"
    )
    ours = next(sec for name, _, sec, _ in rows if name.startswith("rigd BAF (numba"))
    for name, _, sec, _ in rows:
        if name.startswith("dv-processing"):
            print(f"rigd BAF vs {name}: {sec / ours:.2f}x (goal >= 2x at 30 us)")
    print(f"tonic-style keeps exactly what rigd keeps: {same}")


if __name__ == "__main__":
    main()
