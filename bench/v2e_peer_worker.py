"""v2e's side of `bench.event_sim_v2e`: run in v2e's own venv (torch, v2e's source), never
importing rigd, in a process of its own so rigd's numba threads and torch's never share one.

    /path/to/v2e-venv/bin/python bench/v2e_peer_worker.py FRAMES.npy FPS

Prints one JSON line with v2e's version and torch's threads, then reads one JSON object of
`EventEmulator` keyword arguments per line on stdin, runs the frames through a new emulator
(the first frame only sets its state, as in the parent) and answers {"seconds", "events"}.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from importlib.metadata import PackageNotFoundError, version

import numpy as np


def main() -> None:
    import torch
    from v2ecore.emulator import EventEmulator

    logging.getLogger("v2ecore").setLevel(logging.ERROR)
    frames = np.load(sys.argv[1])
    fps = float(sys.argv[2])
    try:
        v2e_version = version("v2e")
    except PackageNotFoundError:
        v2e_version = "(source, version unknown)"
    print(
        json.dumps(
            {
                "note": f"v2e {v2e_version} on torch {torch.__version__} CPU, "
                f"{torch.get_num_threads()} threads, own process"
            }
        ),
        flush=True,
    )
    for line in sys.stdin:
        if not line.strip():
            continue
        kwargs = json.loads(line)
        emu = EventEmulator(device="cpu", seed=0, **kwargs)
        emu.generate_events(frames[0], 0.0)
        n = 0
        t0 = time.perf_counter()
        for i in range(1, len(frames)):
            ev = emu.generate_events(frames[i], i / fps)
            n += 0 if ev is None else len(ev)
        wall = time.perf_counter() - t0
        emu.cleanup()
        print(json.dumps({"seconds": wall, "events": n}), flush=True)


if __name__ == "__main__":
    main()
