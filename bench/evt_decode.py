"""EVT decode/encode throughput of rigd side by side with the `evt3` package and expelliarmus.

    python -m bench.evt_decode [--tiles 40] [--repeat 5] [--file OUT.raw]

Builds a multi-million-event EVT 3.0 RAW file by tiling the real Gen4.1 recording in
../shared/data/events (shifted in time, re-encoded by rigd's encoder so the stream is continuous
and vectorised like the camera's), or a synthetic stream when that file is missing. The process is
pinned to one CPU core so all decoders are compared on one core. Reports the median of N runs
(the machine is shared: medians are the comparable figure) and the best run; decoders are timed
round-robin so background load hits them alike.
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

from rigd.core.events import EventArray, TriggerEvents
from rigd.evt import RawHeader, RawReader, StreamDecoder, encode_evt2, encode_evt3, read_raw, write_raw
from rigd.evt import raw as raw_mod

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


def run_times(fns: list[Callable[[], Any]], repeat: int) -> list[list[float]]:
    """Wall times of each function, interleaved round-robin over `repeat` rounds."""
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(repeat):
        for fn, ts in zip(fns, times, strict=True):
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tiles", type=int, default=40)
    ap.add_argument("--repeat", type=int, default=9)
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

    def check(count: int, name: str) -> None:
        if count != n:
            log.warning("%s decoded %d events, expected %d", name, count, n)

    def chunked() -> None:
        total = 0
        for d in RawReader(path, chunk_bytes=1 << 20):
            total += len(d.events)
        check(total, "rigd chunked")

    def reference_kernel() -> None:
        # the branch-free state machine alone (evt3.decode_kernel), without evt3_fast's loop
        raw_mod.USE_EVT3_FAST = False
        try:
            check(len(read_raw(path)[1].events), "rigd reference kernel")
        finally:
            raw_mod.USE_EVT3_FAST = True

    decoders: list[tuple[str, Callable[[], Any] | None, str]] = [
        ("rigd read_raw (whole file)", lambda: check(len(read_raw(path)[1].events), "rigd"), ""),
        ("rigd read_raw, reference kernel only", reference_kernel, ""),
        ("rigd RawReader (1 MiB chunks)", chunked, ""),
        ("rigd StreamDecoder.feed (bytes in RAM)", lambda: StreamDecoder("evt3").feed(body), ""),
    ]
    try:
        import evt3 as evt3_pkg

        decoders.append(
            ("evt3 (PyPI) decode_file", lambda: check(len(evt3_pkg.decode_file(str(path))), "evt3"), "")
        )
    except ImportError:
        decoders.append(("evt3 (PyPI)", None, "not installed"))
    try:
        from expelliarmus import Wizard

        def expel() -> None:
            arr = Wizard(encoding="evt3", fpath=str(path)).read()
            check(len(arr), "expelliarmus")

        decoders.append(("expelliarmus Wizard.read", expel, ""))
    except ImportError:
        decoders.append(("expelliarmus", None, "not installed"))

    encode_evt3(events[:1000], triggers[:1])  # compile outside the timing (cache=True anyway)
    timed = [(name, fn) for name, fn, _ in decoders if fn is not None]
    for _, warm in timed:
        warm()  # warm-up: compilation, page cache
    all_times = run_times([fn for _, fn in timed], args.repeat)
    dec_times = dict(zip([name for name, _ in timed], all_times, strict=True))
    encoders: list[tuple[str, Callable[[], Any]]] = [
        ("rigd encode_evt3", lambda: encode_evt3(events, triggers)),
        ("rigd encode_evt2", lambda: encode_evt2(events, triggers)),
    ]
    enc_times = run_times([fn for _, fn in encoders], args.repeat)

    def line(name: str, ts: list[float]) -> str:
        med = float(np.median(ts))
        best = min(ts)
        return f"{name:42s} {n / med / 1e6:9.1f} {n / best / 1e6:9.1f} {med:9.4f}"

    header = f"{'Mev/s median':>9s} {'Mev/s best':>9s} {'median (s)':>9s}"
    print(f"\n{'decoder':42s} {header}   ({args.repeat} runs each)")
    for name, maybe_fn, note in decoders:
        if maybe_fn is None:
            print(f"{name:42s} {'-':>9s} {'-':>9s} {'-':>9s}  {note}")
        else:
            print(line(name, dec_times[name]))
    others = [float(np.median(dec_times[k])) for k in dec_times if not k.startswith("rigd")]
    if others:
        fastest = min(others)
        for k in dec_times:
            if k.startswith("rigd") and "reference" not in k:
                ratio = fastest / float(np.median(dec_times[k]))
                print(f"{k} vs fastest other decoder: {ratio:.2f}x (goal >= 1.5x)")
    print(f"\n{'encoder':42s} {header}")
    for (name, _), ts in zip(encoders, enc_times, strict=True):
        print(line(name, ts))


if __name__ == "__main__":
    main()
