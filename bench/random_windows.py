"""Random 50 ms event windows from a long take: chunk size x codec vs read time, write rate, size.

A training job draws random windows of a take (`take.sensor(name).events(t0, t1)`). Each read
decodes every HDF5 chunk of `x, y, p, t` the window overlaps, so the event chunk size sets the
cost of a window, while the writer's append rate and the file size depend on it too. This bench
writes the same realistic event stream (about 1.3 Mev/s on 1280x720, the default sim rig's
sensor) through the real `TakeWriter` append + flush path once per setting, finalizes it, and
times random windows with the reader, and with the reader as it was before the chunk-range
reads (`legacy_window`, the baseline) for the default codec.

    python -m bench.random_windows [--minutes 10] [--sweep-minutes 1] [--windows 400]

The sweep takes are `--sweep-minutes` long; the baseline (262 144-event chunks, lz4) and the
current default are also written at the full `--minutes`, so the table shows the window cost
does not depend on the take's length once the take is much larger than the chunk cache. Reads
come from the page cache (the take was just written): this measures decoding + h5py, not the
disk. The write rate is the writer's own time (append + a flush per second of data, no fsync).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
from numpy.typing import NDArray

from rigd.core.devices import DeviceInfo
from rigd.core.events import EventArray, EventPacket, TriggerEvents
from rigd.core.schema import SyncReport
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.evt import StreamDecoder, encode
from rigd.take import TakeWriter, open_take
from rigd.take.seal import finalize_take

log = logging.getLogger(__name__)

WIDTH, HEIGHT = 1280, 720
SENSOR = "ev0"
#: Events per append, like one driver packet (about 15 ms at 1.3 Mev/s).
PACKET = 20_000
#: Seconds of synthetic events generated once and repeated (shifted in time) to fill a take.
BLOCK_S = 5.0
#: The reader before this bench (commit 1dc254c) opened files with this chunk cache.
_LEGACY_CACHE = 64 << 20
BASELINE = (1 << 18, "lz4")
#: Bytes per driver buffer of the EVT words take (about 10 ms of this stream).
WORD_BUFFER = 32 << 10


def synth_block(seconds: float, rate: float, seed: int = 0) -> EventArray:
    """`seconds` of events at `rate` mean with bursts, clustered along a few moving edges."""
    rng = np.random.default_rng(seed)
    n = int(seconds * rate)
    inst = rate * (1 + 0.8 * np.sin(np.linspace(0, 8 * np.pi * seconds, n)))  # ~4 bursts per second
    t = np.cumsum(rng.exponential(1e6 / inst))
    # Scaled to end just below `seconds`: exactly `rate` on average, and the block repeats
    # (shifted by `seconds`) without time going back.
    t = (t * ((seconds * 1e6 - 1) / t[-1])).astype(np.int64)
    k = 8
    which = rng.integers(0, k, n)
    phase, speed = rng.uniform(0, 2 * np.pi, k), rng.uniform(0.5, 3.0, k)
    ts = t / 1e6
    arg = phase[which] + speed[which] * ts
    cx = WIDTH / 2 + 0.4 * WIDTH * np.sin(arg)
    cy = rng.uniform(0.1, 0.9, k)[which] * HEIGHT + 0.05 * HEIGHT * np.cos(phase[which] + ts)
    x = np.clip(np.rint(cx + rng.normal(0, 8, n)), 0, WIDTH - 1)
    y = np.clip(np.rint(cy + rng.normal(0, 90, n)), 0, HEIGHT - 1)
    p = rng.random(n) < np.where(np.cos(arg) > 0, 0.8, 0.2)
    return EventArray.from_arrays(x, y, p, t)


def packets(block: EventArray, seconds: float) -> list[tuple[int, int, int]]:
    """(shift us, start, stop) of every append: the block repeated for `seconds`."""
    span = int(BLOCK_S * 1e6)
    out = []
    for k in range(int(np.ceil(seconds / BLOCK_S))):
        stop = (
            len(block)
            if (k + 1) * BLOCK_S <= seconds
            else int(np.searchsorted(block.t, (seconds - k * BLOCK_S) * 1e6))
        )
        out += [(k * span, a, min(a + PACKET, stop)) for a in range(0, stop, PACKET)]
    return out


@dataclass
class Timing:
    wall_ms: NDArray[np.float64]
    cpu_ms: NDArray[np.float64]
    window_events: float

    def cells(self) -> str:
        w, c = self.wall_ms, self.cpu_ms
        return (
            f"{np.median(w):7.2f} {np.percentile(w, 99):7.2f} {np.median(c):7.2f} {np.percentile(c, 99):7.2f}"
        )


@dataclass
class Row:
    chunk: int
    codec: str
    minutes: float
    events: int
    write_mev_s: float
    write_cpu_mev_s: float
    bytes_per_event: float
    read: Timing
    legacy: Timing | None


def word_packets(block: EventArray) -> list[EventPacket]:
    """The block as an EVT 3.0 sensor would send it, decoded in driver-sized buffers with the
    production decoder: packets carrying their words (`codec` "evt_words")."""
    data = encode("evt3", block)
    dec = StreamDecoder("evt3", width=WIDTH, height=HEIGHT)
    out = []
    for pos in range(0, len(data), WORD_BUFFER):
        got, chunk = dec.feed_chunk(data[pos : pos + WORD_BUFFER])
        if len(got.events):
            out.append(EventPacket(got.events, got.triggers, 0, chunk))
    return out


def _appends(
    block: EventArray, seconds: float, codec: str, words: list[EventPacket] | None
) -> Iterator[EventPacket]:
    if words is None or codec != "evt_words":
        for shift, a, b in packets(block, seconds):
            yield EventPacket(block[a:b].with_time(block.t[a:b] + shift), TriggerEvents.empty(), 0)
        return
    span = int(BLOCK_S * 1e6)
    for k in range(int(np.ceil(seconds / BLOCK_S))):
        shift = k * span
        for p in words:
            if int(p.events.t[0]) + shift >= seconds * 1e6:
                return
            raw = p.raw
            assert raw is not None
            ev = p.events.with_time(p.events.t + shift)
            yield EventPacket(ev, p.triggers, 0, dataclasses.replace(raw, shift_us=shift))


def write_take(
    path: Path,
    block: EventArray,
    seconds: float,
    chunk: int,
    codec: str,
    words: list[EventPacket] | None = None,
) -> tuple[int, float, float, float]:
    """Write and finalize one take; (events, write Mev/s wall, Mev/s of writer CPU, stored
    bytes/event). Only the writer's calls are timed: append, and a flush per second of data.
    `codec` "evt_words": the sensor's EVT words stored as sent (`word_packets`)."""
    storage = "evt_words" if codec == "evt_words" else "columns"
    cfg = WriterConfig(
        event_chunk=chunk or WriterConfig().event_chunk,
        event_compression="lz4" if codec == "evt_words" else codec,  # type: ignore[arg-type]
        event_storage=storage,  # type: ignore[arg-type]
        fsync=False,
    )
    w = TakeWriter(path, rig_config_json="{}", take_id=path.stem, config=cfg, rigd_version="bench")
    w.add_event_sensor(SENSOR, DeviceInfo(kind="event_sensor", spec="bench"), WIDTH, HEIGHT, "{}", "evt3")
    wall, cpu, n, next_flush = 0.0, 0.0, 0, 1_000_000
    for packet in _appends(block, seconds, codec, words):
        ev = packet.events
        w0, c0 = time.perf_counter(), time.thread_time()
        w.append_packet(SENSOR, packet)
        if int(ev.t[-1]) >= next_flush:
            w.flush()
            next_flush += 1_000_000
        wall, cpu = wall + time.perf_counter() - w0, cpu + time.thread_time() - c0
        n += len(ev)
    w0, c0 = time.perf_counter(), time.thread_time()
    w.flush()
    wall, cpu = wall + time.perf_counter() - w0, cpu + time.thread_time() - c0
    stored = w.stats[SENSOR].stored_bytes
    report = SyncReport(rate_hz=30.0, n_pulses=0, t_first_pulse_us=None, t_last_pulse_us=None)
    finalize_take(w, {SENSOR: ClockMap(0, 0, 1.0)}, {}, report)
    w.close()
    return n, n / wall / 1e6, n / cpu / 1e6, stored / n


def legacy_window(f: h5py.File, t_offset: int, t0: int, t1: int) -> int:
    """The reader's window path before the chunk-range reads: each edge bracketed by
    `ms_to_idx` and searched in its own read of `t`, then `x, y, p, t` read again, every
    dataset looked up afresh (so its chunk cache starts empty). Returns the event count."""
    g = f[f"events/{SENSOR}"]

    def first(rel: int, n: int) -> int:
        ms = g["ms_to_idx"]
        n_ms = int(ms.shape[0])
        a, b = rel // 1000, max(-(-rel // 1000), 0)
        lo = 0 if a < 0 else (n if a >= n_ms else int(ms[a]))
        hi = n if b >= n_ms else int(ms[b])
        return lo if lo >= hi else lo + int(np.searchsorted(g["t"][lo:hi], rel, side="left"))

    n = int(g["t"].shape[0])
    lo, hi = first(t0 - t_offset, n), first(t1 - t_offset, n)
    hi = max(lo, hi)
    t = np.asarray(g["t"][lo:hi], dtype=np.int64) + t_offset
    p = g["p"][lo:hi].astype(np.int8) * np.int8(2) - np.int8(1)
    EventArray(g["x"][lo:hi], g["y"][lo:hi], p, t)
    return hi - lo


def time_windows(path: Path, starts: NDArray[np.int64], window_us: int, legacy: bool) -> Timing:
    """Per window read (after 3 untimed ones): wall ms, and this thread's CPU ms, which other
    processes on a shared machine do not inflate; and the mean events per window."""
    wall, cpu, counts = [], [], []
    with h5py.File(path, "r", rdcc_nbytes=_LEGACY_CACHE, rdcc_nslots=10007) as f, open_take(path) as take:
        off = int(f[f"events/{SENSOR}/t_offset"][()])
        for i, s in enumerate(starts):
            w0, c0 = time.perf_counter(), time.thread_time()
            if legacy:
                k = legacy_window(f, off, int(s), int(s) + window_us)
            else:
                k = len(take.sensor(SENSOR).events(int(s), int(s) + window_us))
            if i >= 3:
                wall.append(time.perf_counter() - w0)
                cpu.append(time.thread_time() - c0)
                counts.append(k)
    return Timing(np.asarray(wall) * 1e3, np.asarray(cpu) * 1e3, float(np.mean(counts)))


def run_one(
    tmp: Path,
    block: EventArray,
    minutes: float,
    chunk: int,
    codec: str,
    args: argparse.Namespace,
    words: list[EventPacket] | None = None,
) -> Row:
    path = tmp / f"rw-{chunk}-{codec}-{minutes:g}.h5"
    n, rate, rate_cpu, bpe = write_take(path, block, minutes * 60, chunk, codec, words)
    window_us = int(args.window_ms * 1000)
    with open_take(path) as take:
        span = take.sensor(SENSOR).span
    if span is None:
        raise RuntimeError(f"{path}: no events written")
    starts = np.random.default_rng(args.seed).integers(span[0], span[1] - window_us, args.windows + 3)
    read = time_windows(path, starts, window_us, legacy=False)
    legacy = time_windows(path, starts, window_us, legacy=True) if codec == BASELINE[1] else None
    path.unlink()
    print(
        f"  chunk {chunk:>7} {codec:5} {minutes:g} min: {n / 1e6:.0f} Mev, "
        f"read {np.median(read.wall_ms):.2f} ms, write {rate:.1f} Mev/s",
        flush=True,
    )
    return Row(chunk, codec, minutes, n, rate, rate_cpu, bpe, read, legacy)


def print_table(rows: list[Row], default: tuple[int, str]) -> None:
    read_hdr = f"{'median':>7} {'p99':>7} {'cpu med':>7} {'cpu p99':>7}"
    hdr = (
        f"{'chunk':>7} {'codec':5} {'min':>4} | read: {read_hdr} | old reader: {read_hdr} | "
        f"{'write Mev/s':>11} {'(cpu)':>6} | {'B/event':>7}  note"
    )
    print(hdr)
    print("-" * len(hdr))
    blank = f"{'-':>7} {'-':>7} {'-':>7} {'-':>7}"
    for r in rows:
        note = [
            label
            for label, key in (("old default", BASELINE), ("default", default))
            if (r.chunk, r.codec) == key
        ]
        print(
            f"{r.chunk:>7} {r.codec:5} {r.minutes:>4g} |       {r.read.cells()} |             "
            f"{r.legacy.cells() if r.legacy else blank} | {r.write_mev_s:11.1f} {r.write_cpu_mev_s:6.1f} | "
            f"{r.bytes_per_event:7.2f}  {', '.join(note)}".rstrip()
        )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--minutes", type=float, default=10.0, help="Length of the baseline and default takes.")
    ap.add_argument("--sweep-minutes", type=float, default=1.0, help="Length of the other takes.")
    ap.add_argument(
        "--full",
        default="",
        help="More CHUNK:CODEC settings written at the full --minutes (besides the old and current default).",
    )
    ap.add_argument("--chunks", default="16384,32768,65536,131072,262144")
    ap.add_argument("--codecs", default="lz4,zstd,none")
    ap.add_argument("--rate", type=float, default=1.3e6, help="Mean events/s of the sensor.")
    ap.add_argument("--windows", type=int, default=400)
    ap.add_argument("--window-ms", type=float, default=50.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--evt-words",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="Also a take of EVT words as sent (the default storage of EVT sensors; chunk column 0).",
    )
    ap.add_argument("--dir", type=Path, default=None, help="Where to write (default: a temp dir).")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    cfg = WriterConfig()
    default = (cfg.event_chunk, cfg.event_compression)  # of the columns layout (DAT replays, old takes)
    chunks = [int(c) for c in args.chunks.split(",")]
    codecs = args.codecs.split(",")
    print(
        f"synthesising {BLOCK_S:g} s of events at {args.rate / 1e6:.2f} Mev/s ({WIDTH}x{HEIGHT}) ...",
        flush=True,
    )
    block = synth_block(BLOCK_S, args.rate)
    rows: list[Row] = []
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        extra = [(int(c), k) for c, k in (item.split(":") for item in args.full.split(",") if item)]
        for chunk, codec in dict.fromkeys([BASELINE, default, *extra]):
            rows.append(run_one(Path(tmp), block, args.minutes, chunk, codec, args))
        if args.evt_words:
            words = word_packets(block)
            rows.append(run_one(Path(tmp), block, args.minutes, 0, "evt_words", args, words))
        for codec in codecs:
            for chunk in chunks:
                rows.append(run_one(Path(tmp), block, args.sweep_minutes, chunk, codec, args))
    print(
        f"\n{args.window_ms:g} ms windows at {args.rate / 1e6:.2f} Mev/s "
        f"(mean {rows[0].read.window_events:,.0f} events), {args.windows} random windows per take, "
        f"{time.perf_counter() - t_start:.0f} s in all; read = Take.events, "
        "old reader = the window path before chunk-range reads; ms"
    )
    print_table(rows, default)


if __name__ == "__main__":
    main()
