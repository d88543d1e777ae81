"""Canonical keyframe selection (paper Eq. 3): brute force O(n^2) vs the sort + prefix-sum O(n log n).

Maps are what `partition` builds: signed event counts accumulated over time (random walks per
pixel), at a small and at the default-scale map size. The brute force is skipped where its
quadratic extrapolation from the previous size exceeds `--max-brute-s` (10 s).

    python -m bench.keyframe [--max-brute-s 10]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from reconstruction.partition import canonical_keyframe, canonical_keyframe_bruteforce

CASES = [
    (16, 12, [10, 100, 1_000, 3_000, 10_000, 100_000]),
    (80, 60, [10, 100, 300, 1_000, 3_000, 10_000]),
]


def walk_maps(n: int, w: int, h: int, seed: int = 0) -> NDArray[np.float32]:
    rng = np.random.default_rng(seed)
    steps = rng.integers(-1, 2, (n, h, w), dtype=np.int8)
    return np.cumsum(steps, axis=0, dtype=np.int32).astype(np.float32)


def timed(fn: Callable[[NDArray[np.float32]], int], maps: NDArray[np.float32]) -> tuple[int, float]:
    t0 = time.perf_counter()
    k = fn(maps)
    return int(k), time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--max-brute-s", type=float, default=10.0)
    args = ap.parse_args()
    print("| n maps | map (w x h) | brute force s | new s | speedup | same result |")
    print("|---:|---|---:|---:|---:|---|")
    for w, h, sizes in CASES:
        last: tuple[int, float] | None = None
        for n in sizes:
            maps = walk_maps(n, w, h)
            k_new, t_new = timed(canonical_keyframe, maps)
            est = None if last is None else last[1] * (n / last[0]) ** 2
            if est is not None and est > args.max_brute_s:
                brute, speed, same = f"skipped (~{est:.0f} s est.)", "", "n/a"
            else:
                k_ref, t_ref = timed(canonical_keyframe_bruteforce, maps)
                last = (n, t_ref)
                brute, speed, same = (
                    f"{t_ref:.4f}",
                    f"{t_ref / t_new:.1f}x",
                    "yes" if k_ref == k_new else "NO",
                )
            print(f"| {n} | {w} x {h} | {brute} | {t_new:.4f} | {speed} | {same} |", flush=True)


if __name__ == "__main__":
    main()
