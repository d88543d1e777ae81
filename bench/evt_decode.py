"""EVT 3.0 decode throughput of rigd beside evt3 and expelliarmus, on the bytes a camera sends.

    python -m bench.evt_decode [--tiles 60] [--repeat 9] [--peer-python /tmp/peers/bin/python]

The file decoded is the real Gen4.1 recording (../shared/data/events/evt3_gen41_sample.raw)
tiled end to end: its words are copied as they are and only the TIME_HIGH words of each copy are
shifted so time goes on from one copy to the next (never decoded and re-encoded: the vectors,
ADDR_Y runs and repeated TIME_HIGHs are the sensor's). Bytes per event is reported, since a
re-encoded stream packs differently. The peers run their own code, unmodified, in their own venv
(`--peer-python`: a python with `pip install evt3 expelliarmus`; a worker process,
bench/evt_peer_worker.py, so they never share rigd's imports), one decode per round,
interleaved round-robin with rigd's so background load hits all alike. Every decoder and the
worker run pinned to the same one CPU core. Whole-file calls and streaming readers (1 MiB
chunks) are compared, each mode against the peers' same mode; memcpy GB/s of the file's size
is measured in the same rounds as the machine's limit. Each call's wall-clock time and its
process's CPU time are both reported: on a core other processes share, the CPU time is what the
decode itself cost. rigd's EVT 3.0 and 2.0 encoders are timed last, on the decoded events.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from bench.peer_process import PeerProcess
from rigd.evt import RawReader, StreamDecoder, encode_evt2, encode_evt3, parse_raw_header, read_raw
from rigd.evt import raw as raw_mod

log = logging.getLogger(__name__)

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "events" / "evt3_gen41_sample.raw"
DEFAULT_PEERS = Path("/tmp/scratch-perf/bin/python")
WORKER = Path(__file__).resolve().with_name("evt_peer_worker.py")
#: TIME_HIGH: 4-bit type 0x8, 12 bits of time in units of 4096 us.
_TIME_HIGH, _TH_UNIT_US = 0x8, 4096


def tile_words(path: Path, tiles: int) -> tuple[bytes, NDArray[np.uint16]]:
    """The file's header and its EVT 3.0 words from the first TIME_HIGH on, `tiles` times end to
    end; copy k's TIME_HIGH values are raised by k spans (12-bit, wrapping as a sensor's do), so
    the tiled stream is one continuous recording of k times the time."""
    with path.open("rb") as f:
        header = parse_raw_header(f)
        if header.fmt != "evt3":
            raise SystemExit(f"{path}: {header.fmt}, not EVT 3.0")
        f.seek(0)
        head = f.read(header.size)
        body = f.read()
    words = np.frombuffer(body[: len(body) // 2 * 2], np.uint16)
    is_th = (words >> 12) == _TIME_HIGH
    first = int(np.argmax(is_th))
    if not is_th.any():
        raise SystemExit(f"{path}: no TIME_HIGH word")
    words = words[first:]
    is_th = is_th[first:]
    th = (words[is_th] & 0xFFF).astype(np.int64)
    unwrapped = th + 4096 * np.concatenate([[0], np.cumsum(np.diff(th) < -2048)])
    span = int(unwrapped[-1] - unwrapped[0]) + 1  # TIME_HIGH units one copy covers
    out = np.tile(words, tiles)
    th_pos = np.flatnonzero(np.tile(is_th, tiles))
    shift = np.repeat(np.arange(tiles, dtype=np.int64) * span, int(is_th.sum()))
    out[th_pos] = (_TIME_HIGH << 12) | ((out[th_pos].astype(np.int64) + shift) & 0xFFF)
    return head, out


class Peers(PeerProcess):
    """The worker process that runs the peers' decoders in their own venv."""

    def __init__(self, python: Path, path: Path, cpu: int | None) -> None:
        super().__init__([str(python), str(WORKER), str(path)], cpu=cpu, close_timeout_s=30.0)
        self.names: list[str] = self.hello["names"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tiles", type=int, default=60)
    ap.add_argument("--repeat", type=int, default=9)
    ap.add_argument("--file", type=Path, default=None, help="Where to write the tiled file.")
    ap.add_argument("--source", type=Path, default=REAL, help="The EVT 3.0 recording to tile.")
    ap.add_argument(
        "--peer-python",
        type=Path,
        default=Path(os.environ.get("RIGD_BENCH_PEER_PYTHON", str(DEFAULT_PEERS))),
        help="A python with evt3 and expelliarmus installed (their own venv).",
    )
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    cpu = None
    if hasattr(os, "sched_setaffinity"):
        cpu = sorted(os.sched_getaffinity(0))[0]
        os.sched_setaffinity(0, {cpu})

    head, words = tile_words(args.source, args.tiles)
    path = args.file or Path(tempfile.mkdtemp()) / "bench_evt3_tiled.raw"
    with path.open("wb") as f:
        f.write(head)
        f.write(words.tobytes())
    size = path.stat().st_size
    n = len(read_raw(path)[1].events)
    body = path.read_bytes()[len(head) :]
    print(
        f"file: {path}: {args.source.name} tiled x{args.tiles} (TIME_HIGH shifted, not re-encoded): "
        f"{n / 1e6:.2f} M events, {size / 1e6:.1f} MB, {len(body) / n:.2f} B/event; 1 core (cpu {cpu})"
    )

    src = np.frombuffer(body, np.uint8)
    dst = np.empty_like(src)

    def memcpy() -> int:
        np.copyto(dst, src)
        return n

    def chunked() -> int:
        return sum(len(d.events) for d in RawReader(path, chunk_bytes=1 << 20))

    def reference_kernel() -> int:
        # the branch-free state machine alone (evt3.decode_kernel), without evt3_fast's loop
        raw_mod.USE_EVT3_FAST = False
        try:
            return len(read_raw(path)[1].events)
        finally:
            raw_mod.USE_EVT3_FAST = True

    ours: dict[str, Callable[[], int]] = {
        "rigd read_raw (whole file)": lambda: len(read_raw(path)[1].events),
        "rigd StreamDecoder.feed (whole body in RAM)": lambda: len(StreamDecoder("evt3").feed(body).events),
        "rigd read_raw, reference kernel only": reference_kernel,
        "rigd RawReader (1 MiB chunks)": chunked,
        "memcpy of the body (np.copyto)": memcpy,
    }
    peers = Peers(args.peer_python, path, cpu) if args.peer_python.exists() else None
    if peers is None:
        print(f"peers: {args.peer_python} not found (pip install evt3 expelliarmus into a venv there)")
    names = list(ours) + (peers.names if peers else [])
    times: dict[str, list[float]] = {k: [] for k in names}
    cpu_times: dict[str, list[float]] = {k: [] for k in names}
    counts: dict[str, int] = {}
    try:
        for rnd in range(args.repeat + 1):  # round 0 warms up: compilation, page cache
            for name in names:
                if name in ours:
                    t0, c0 = time.perf_counter(), time.process_time()
                    count = ours[name]()
                    dt, ct = time.perf_counter() - t0, time.process_time() - c0
                else:
                    assert peers is not None
                    answer = peers.ask(name)
                    dt, ct = float(answer["seconds"]), float(answer["cpu_seconds"])
                    count = int(answer["events"])
                counts[name] = count
                if rnd:
                    times[name].append(dt)
                    cpu_times[name].append(ct)
    finally:
        if peers is not None:
            peers.close()
    _report(names, times, cpu_times, counts, n, len(body))
    _encoders(path, args.repeat)


def _encoders(path: Path, repeat: int) -> None:
    """rigd's encoders on the decoded events and triggers of the same file, interleaved."""
    dec = read_raw(path)[1]
    events, triggers = dec.events, dec.triggers
    fns = {"rigd encode_evt3": encode_evt3, "rigd encode_evt2": encode_evt2}
    for fn in fns.values():
        fn(events[:1000], triggers[:1])  # compile (or load from the cache) outside the timing
    times: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeat):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn(events, triggers)
            times[name].append(time.perf_counter() - t0)
    print(f"\n{'encoder':46s} {'Mev/s med':>9s} {'Mev/s best':>10s}")
    for name, ts in times.items():
        print(
            f"{name:46s} {len(events) / float(np.median(ts)) / 1e6:9.1f} {len(events) / min(ts) / 1e6:10.1f}"
        )


def _report(
    names: list[str],
    times: dict[str, list[float]],
    cpu_times: dict[str, list[float]],
    counts: dict[str, int],
    n: int,
    nbytes: int,
) -> None:
    med = {k: float(np.median(v)) for k, v in times.items()}
    cpu = {k: float(np.median(v)) for k, v in cpu_times.items()}
    rounds = len(next(iter(times.values())))
    load1, load5, _ = os.getloadavg()
    print(f"load: {load1:.2f} {load5:.2f} (1, 5 min averages, 2 cores shared); {rounds} rounds")
    print(
        f"\n{'decoder':46s} {'Mev/s med':>9s} {'Mev/s best':>10s} {'MB/s med':>9s} {'median s':>9s} "
        f"{'CPU Mev/s':>9s}  events"
    )
    for k in names:
        best = min(times[k])
        mark = "" if counts[k] == n else f"  (!= {n})"
        print(
            f"{k:46s} {n / med[k] / 1e6:9.1f} {n / best / 1e6:10.1f} {nbytes / med[k] / 1e6:9.0f} "
            f"{med[k]:9.4f} {n / cpu[k] / 1e6:9.1f}  {counts[k]}{mark}"
        )
    memcpy = med["memcpy of the body (np.copyto)"]
    print(f"\nmachine limit: memcpy {nbytes / memcpy / 1e9:.1f} GB/s on this core, this run")
    print("ratios: wall-clock medians (CPU-time medians: what each decode cost where others share the core)")
    modes = {
        "whole file": ("rigd read_raw (whole file)", ("evt3 decode_file (", "expelliarmus Wizard.read")),
        "streaming": (
            "rigd RawReader (1 MiB chunks)",
            ("evt3 decode_file_batches", "expelliarmus read_chunk"),
        ),
    }
    for mode, (ours, prefixes) in modes.items():
        peers = [k for k in names if k.startswith(prefixes)]
        for k in peers:
            ratio, cpu_ratio = med[k] / med[ours], cpu[k] / cpu[ours]
            print(f"{mode}: {ours} vs {k}: {ratio:.2f}x ({cpu_ratio:.2f}x CPU) (goal >= 2x)")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
