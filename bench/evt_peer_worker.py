"""The EVT 3.0 peers' side of `bench.evt_decode`: run in the peers' own venv (evt3 and
expelliarmus, unmodified, installed from PyPI), never importing rigd.

    /path/to/peer-venv/bin/python bench/evt_peer_worker.py FILE.raw

Reads one decoder name per line on stdin, decodes FILE.raw with it once, pinned to the CPU the
parent gives it, and answers one JSON line: {"name", "seconds", "events"}. The parent interleaves
these runs with its own decoders' (round-robin), so background load hits all of them alike.
`cpu_seconds` is the process's CPU time for the call (all its threads; on the one core they are
pinned to): what the decode cost where other processes share the core.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable


def decoders(path: str) -> dict[str, Callable[[], int]]:
    """name -> a call that decodes the whole file and returns the events it decoded."""
    out: dict[str, Callable[[], int]] = {}
    try:
        import evt3

        out["evt3 decode_file (whole file)"] = lambda: len(evt3.decode_file(path))

        def evt3_batches() -> int:
            return sum(len(b) for b in evt3.decode_file_batches(path, batch_bytes=1 << 20))

        out["evt3 decode_file_batches (1 MiB)"] = evt3_batches
    except ImportError:
        pass
    try:
        from expelliarmus import Wizard

        out["expelliarmus Wizard.read (whole file)"] = lambda: len(Wizard(encoding="evt3", fpath=path).read())

        def expel_chunks() -> int:
            # expelliarmus' streaming reader: its chunk is counted in events; 1 MiB of this
            # file's words is ~370 k events
            w = Wizard(encoding="evt3", fpath=path, chunk_size=370_000)
            return sum(len(c) for c in w.read_chunk())

        out["expelliarmus read_chunk (~1 MiB)"] = expel_chunks
    except ImportError:
        pass
    return out


def main() -> None:
    fns = decoders(sys.argv[1])
    print(json.dumps({"names": list(fns)}), flush=True)
    for line in sys.stdin:
        name = line.strip()
        if not name:
            continue
        t0, c0 = time.perf_counter(), time.process_time()
        n = fns[name]()
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        print(json.dumps({"name": name, "seconds": wall, "cpu_seconds": cpu, "events": n}), flush=True)


if __name__ == "__main__":
    main()
