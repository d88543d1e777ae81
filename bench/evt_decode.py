"""EVT decode/encode throughput of rigd side by side with the `evt3` package and expelliarmus.

    python -m bench.evt_decode [--tiles 40] [--repeat 5] [--file OUT.raw]

Builds a multi-million-event EVT 3.0 RAW file by tiling the real Gen4.1 recording in
../shared/data/events (shifted in time, re-encoded by rigd's encoder so the stream is continuous
and vectorised like the camera's), or a synthetic stream when that file is missing. The process is
pinned to one CPU core so all decoders are compared on one core. Reports best-of-N wall time.
"""

from __future__ import annotations

import argparse
import logging
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from drivers.evt import RawHeader, RawReader, StreamDecoder, encode_evt2, encode_evt3, read_raw, write_raw
from rigd.core.events import EventArray, TriggerEvents

log = logging.getLogger(__name__)

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "events" / "evt3_gen41_sample.raw"


def build_events(tiles: int) -> tuple[EventArray, TriggerEvents]:
    """Real readout structure repeated in time; synthetic rows of bursts if the file is absent."""
    if REAL.exists():
        _, dec = read_raw(REAL)
        base = dec.events
    else:
        rng = np.random.default_rng(0)
        n = 200_000
        t = np.sort(rng.integers(0, 10_000, n))
        base = EventArray.from_arrays(
            rng.integers(0, 1280, n), rng.integers(0, 720, n), rng.integers(0, 2, n), t
        )
    t0 = int(base.t[0])
    span = int(base.t[-1]) - t0 + 1
    parts = [base.with_time(base.t - t0 + k * span) for k in range(tiles)]
    events = EventArray.concatenate(parts)
    trig_t = np.arange(0, tiles * span, 1000, dtype=np.int64)
    triggers = TriggerEvents(
        trig_t, (np.arange(trig_t.size) % 2).astype(np.uint8), np.zeros(trig_t.size, np.uint8)
    )
    return events, triggers


def best_time(fn: Callable[[], Any], repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tiles", type=int, default=40)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--file", type=Path, default=None)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    os.environ.setdefault("RAYON_NUM_THREADS", "1")

    events, triggers = build_events(args.tiles)
    n = len(events)
    path = args.file or Path(tempfile.mkdtemp()) / "bench_evt3.raw"
    # no triggers in the decode file: expelliarmus rejects EXT_TRIGGER words ("event type not recognised")
    write_raw(path, RawHeader(fmt="evt3", width=1280, height=720), events)
    size = path.stat().st_size
    payload = path.read_bytes()
    hdr_size = len(RawHeader(fmt="evt3").to_bytes())
    body = payload[hdr_size:]
    print(f"file: {path}  {n / 1e6:.2f} M events, {size / 1e6:.1f} MB ({size / n:.2f} B/event), 1 core")

    rows: list[tuple[str, float, str]] = []

    def check(count: int, name: str) -> None:
        if count != n:
            log.warning("%s decoded %d events, expected %d", name, count, n)

    encode_evt3(events[:1000], triggers[:1])  # compile outside the timing (cache=True anyway)
    read_raw(path)
    rows.append(
        (
            "rigd read_raw (whole file)",
            best_time(lambda: check(len(read_raw(path)[1].events), "rigd"), args.repeat),
            "",
        )
    )

    def chunked() -> None:
        total = 0
        for d in RawReader(path, chunk_bytes=1 << 20):
            total += len(d.events)
        check(total, "rigd chunked")

    rows.append(("rigd RawReader (1 MiB chunks)", best_time(chunked, args.repeat), ""))
    rows.append(
        (
            "rigd StreamDecoder.feed (bytes in RAM)",
            best_time(lambda: StreamDecoder("evt3").feed(body), args.repeat),
            "",
        )
    )
    try:
        import evt3 as evt3_pkg

        rows.append(
            (
                "evt3 (PyPI) decode_file",
                best_time(lambda: check(len(evt3_pkg.decode_file(str(path))), "evt3"), args.repeat),
                "",
            )
        )
    except ImportError:
        rows.append(("evt3 (PyPI)", float("nan"), "not installed"))
    try:
        from expelliarmus import Wizard

        def expel() -> None:
            arr = Wizard(encoding="evt3", fpath=str(path)).read()
            check(len(arr), "expelliarmus")

        rows.append(("expelliarmus Wizard.read", best_time(expel, args.repeat), ""))
    except ImportError:
        rows.append(("expelliarmus", float("nan"), "not installed"))

    enc_rows = [
        ("rigd encode_evt3", best_time(lambda: encode_evt3(events, triggers), args.repeat)),
        ("rigd encode_evt2", best_time(lambda: encode_evt2(events, triggers), args.repeat)),
    ]

    print(f"\n{'decoder':42s} {'Mev/s':>9s} {'time (s)':>9s}")
    for name, sec, note in rows:
        if note:
            print(f"{name:42s} {'-':>9s} {'-':>9s}  {note}")
        else:
            print(f"{name:42s} {n / sec / 1e6:9.1f} {sec:9.4f}")
    print(f"\n{'encoder':42s} {'Mev/s':>9s} {'time (s)':>9s}")
    for name, sec in enc_rows:
        print(f"{name:42s} {n / sec / 1e6:9.1f} {sec:9.4f}")


if __name__ == "__main__":
    main()
