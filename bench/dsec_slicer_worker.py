"""DSEC's EventSlicer side of `bench.window_reads`: run with the peer's own python (a venv with
h5py, hdf5plugin, numba and numpy), never importing rigd; DSEC's `scripts/utils/eventslicer.py`
is imported from a checkout of its repository, unmodified.

    /path/to/peer-venv/bin/python bench/dsec_slicer_worker.py DSEC_REPO EVENTS_H5 [CPU]

Opens EVENTS_H5 (`rigd export --format dsec`: events/<sensor>/events.h5) once with
`EventSlicer(h5py.File(...))`, as DSEC's loaders do, prints one JSON line (versions, events,
t_offset), then answers each request line `T0 T1` (the export's us) with one JSON line:
`{"seconds": ..., "cpu": ..., "events": ..., "digest": ...}` (wall and this thread's CPU
seconds). Only `get_events` is timed; the digest
(sha1 of x, y as uint16, p as uint8 and t as int64, in that order) is computed after it.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from pathlib import Path

import h5py
import numpy as np


def digest(x: np.ndarray, y: np.ndarray, p: np.ndarray, t: np.ndarray) -> str:
    h = hashlib.sha1()
    for a, dt in ((x, np.uint16), (y, np.uint16), (p, np.uint8), (t, np.int64)):
        h.update(np.ascontiguousarray(a, dtype=dt).tobytes())
    return h.hexdigest()


def main() -> None:
    repo, path = Path(sys.argv[1]), sys.argv[2]
    if len(sys.argv) > 3:
        os.sched_setaffinity(0, {int(sys.argv[3])})
    sys.path.insert(0, str(repo / "scripts" / "utils"))
    import numba
    from eventslicer import EventSlicer

    with h5py.File(path, "r") as f:
        slicer = EventSlicer(f)
        print(
            json.dumps(
                {
                    "peer": f"DSEC EventSlicer ({repo / 'scripts' / 'utils' / 'eventslicer.py'})",
                    "versions": f"numpy {np.__version__}, h5py {h5py.__version__}, numba {numba.__version__}",
                    "events": int(f["events/t"].shape[0]),
                    "t_offset": slicer.get_start_time_us(),
                    "t_final": slicer.get_final_time_us(),
                    "ms_to_idx": int(slicer.ms_to_idx.size),
                }
            ),
            flush=True,
        )
        for line in sys.stdin:
            if not line.strip():
                continue
            a, b = (int(v) for v in line.split())
            t0, c0 = time.perf_counter(), time.thread_time()
            ev = slicer.get_events(a, b)
            seconds, cpu = time.perf_counter() - t0, time.thread_time() - c0
            if ev is None:
                print(json.dumps({"seconds": seconds, "cpu": cpu, "events": -1, "digest": ""}), flush=True)
                continue
            d = digest(ev["x"], ev["y"], ev["p"], ev["t"])
            answer = {"seconds": seconds, "cpu": cpu, "events": int(ev["t"].size), "digest": d}
            print(json.dumps(answer), flush=True)


if __name__ == "__main__":
    main()
