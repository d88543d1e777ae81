"""dv-processing's side of `bench.reconstruction_filter`: runs under dv-processing's own venv
(installed from PyPI, unmodified) and never imports rigd.

    /path/to/peer-venv/bin/python bench/dv_peer_worker.py EVENTS.npz WIDTH HEIGHT

Loads the events (arrays x, y, p, t), builds one dv.EventStore (not timed) and prints one JSON
line {"peer", "events", "store_s"}. Then it answers each request line, a background-activity
duration in us, with one JSON line {"seconds", "events", "kept"}: a fresh
BackgroundActivityNoiseFilter, accept() of the whole store and generateEvents(), timed here. The
parent pins this process to its own core and interleaves these runs with rigd's.
"""

from __future__ import annotations

import json
import sys
import time
from datetime import timedelta


def main() -> None:
    import dv_processing as dv
    import numpy as np

    path, width, height = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    with np.load(path) as d:
        x, y, p, t = (d[k] for k in ("x", "y", "p", "t"))
    t0 = time.perf_counter()
    store = dv.EventStore()
    for ti, xi, yi, pi in zip(t.tolist(), x.tolist(), y.tolist(), (p > 0).tolist(), strict=True):
        store.push_back(ti, xi, yi, pi)
    version = getattr(dv, "__version__", "?")
    hello = {"peer": f"dv-processing {version}", "events": store.size(), "store_s": time.perf_counter() - t0}
    print(json.dumps(hello), flush=True)
    for line in sys.stdin:
        if not line.strip():
            continue
        duration_us = int(line)
        t0 = time.perf_counter()
        f = dv.noise.BackgroundActivityNoiseFilter(
            (width, height), backgroundActivityDuration=timedelta(microseconds=duration_us)
        )
        f.accept(store)
        kept = f.generateEvents().size()
        seconds = time.perf_counter() - t0
        print(json.dumps({"seconds": seconds, "events": store.size(), "kept": kept}), flush=True)


if __name__ == "__main__":
    main()
