"""Event storage on the real Gen4.1 stream: EVT words as sent vs decoded x/y/p/t columns.

The real EVT 3.0 recording is cut into driver-sized buffers and decoded once with the
production `StreamDecoder.feed_chunk` (as `DecodingEventSensor` does), giving the packets a capture
hands the writer. They are then written, repeated with their times shifted on (each repeat's
chunk says so in `shift_us`, as a re-tied clock does), through the real `TakeWriter` into a take
on disk with fsync at every flush (one per second of data) and on close, once per storage. The
writer's time is only that spent in `append_packet`, `flush` and `close` (thread CPU time
beside it: one core). The disk's own rate is a plain write of the same byte count with fsync,
measured in the same run. B/ev on disk is measured on one pass of the recording (no repeat:
a repeated stream would compress better than a real one).

    python -m bench.event_storage [--seconds 2] [--finalize-seconds 60] [--dir DIR]

`--finalize-seconds`: length (at 20 Mev/s) of the take whose finalize is timed per storage;
the columns take is timed at `--seconds` instead (its finalize rewrites every event time, so
its cost grows with the events; scaled in the table).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from rigd.core.devices import DeviceInfo
from rigd.core.events import EventPacket, TriggerEvents
from rigd.core.schema import SyncReport
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.evt import StreamDecoder, parse_raw_header, warm_up_decoder
from rigd.take import TakeWriter
from rigd.take.seal import finalize_take

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "events" / "evt3_gen41_sample.raw"
#: Bytes per driver buffer (OpenEB's default HAL buffers are of this order).
BUFFER = 64 << 10
SENSOR = "ev0"
RATE = 20e6


@dataclass(frozen=True)
class Source:
    packets: list[EventPacket]
    width: int
    height: int
    events: int
    words: int
    span_us: int
    decode_s: float


def load(path: Path) -> Source:
    with path.open("rb") as f:
        hdr = parse_raw_header(f)
        body = f.read()
    warm_up_decoder(hdr.fmt, hdr.width, hdr.height)
    dec = StreamDecoder(hdr.fmt, width=hdr.width, height=hdr.height)
    t0 = time.perf_counter()
    packets = []
    for pos in range(0, len(body), BUFFER):
        got, chunk = dec.feed_chunk(body[pos : pos + BUFFER])
        packets.append(EventPacket(got.events, got.triggers, 0, chunk))
    got, last = dec.flush_chunk()
    if last is not None:
        packets.append(EventPacket(got.events, got.triggers, 0, last))
    took = time.perf_counter() - t0
    n = sum(len(p.events) for p in packets)
    t = [p.events.t for p in packets if len(p.events)]
    span = int(t[-1][-1]) - int(t[0][0]) + 1
    words = sum(len(p.raw.data) for p in packets if p.raw is not None)
    return Source(packets, hdr.width, hdr.height, n, words, span, took)


def repeated(src: Source, reps: int) -> Iterator[tuple[int, EventPacket]]:
    """(repeat, packet) with each repeat's times shifted on by the recording's span."""
    for k in range(reps):
        shift = k * src.span_us
        for p in src.packets:
            if not shift:
                yield k, p
                continue
            raw = p.raw
            assert raw is not None
            yield (
                k,
                EventPacket(
                    p.events.with_time(p.events.t + shift),
                    TriggerEvents(p.triggers.t + shift, p.triggers.p, p.triggers.channel),
                    0,
                    dataclasses.replace(raw, shift_us=shift),
                ),
            )


@dataclass
class Result:
    storage: str
    events: int
    wall_s: float
    cpu_s: float
    file_bytes: int
    stored_bytes: int
    """The events' own datasets (evt_words; x, y, p, t)."""
    index_bytes: int
    """Their index (evt_index; ms_to_idx)."""
    finalize_s: float


def write(path: Path, src: Source, storage: str, reps: int, *, finalize: bool) -> Result:
    cfg = WriterConfig(event_storage=storage, fsync=True)  # type: ignore[arg-type]
    w = TakeWriter(path, rig_config_json="{}", take_id=path.stem, config=cfg, rigd_version="bench")
    w.add_event_sensor(
        SENSOR, DeviceInfo(kind="event_sensor", spec="bench"), src.width, src.height, "{}", "evt3"
    )
    flush_every = max(1, round(1e6 / src.span_us))  # one flush per second of data
    wall = cpu = 0.0
    last = 0
    for k, packet in repeated(src, reps):
        if k != last and k % flush_every == 0:
            a, c = time.perf_counter(), time.thread_time()
            w.flush()
            wall += time.perf_counter() - a
            cpu += time.thread_time() - c
        last = k
        a, c = time.perf_counter(), time.thread_time()
        w.append_packet(SENSOR, packet)
        wall += time.perf_counter() - a
        cpu += time.thread_time() - c
    fin = 0.0
    a, c = time.perf_counter(), time.thread_time()
    if finalize:
        w.flush()
        wall += time.perf_counter() - a
        cpu += time.thread_time() - c
        report = SyncReport(rate_hz=30.0, n_pulses=0, t_first_pulse_us=None, t_last_pulse_us=None)
        f0 = time.perf_counter()
        finalize_take(w, {SENSOR: ClockMap(0, 1_000, 1.00001, 0.25)}, {}, report)
        fin = time.perf_counter() - f0
        a, c = time.perf_counter(), time.thread_time()
    w.close()
    wall += time.perf_counter() - a
    cpu += time.thread_time() - c
    with h5py.File(path, "r") as f:
        g = f[f"events/{SENSOR}"]
        names = ("evt_words",) if storage == "evt_words" else ("x", "y", "p", "t")
        stored = sum(g[k].id.get_storage_size() for k in names)
        index = sum(g[k].id.get_storage_size() for k in ("evt_index", "ms_to_idx") if k in g)
    return Result(storage, src.events * reps, wall, cpu, path.stat().st_size, stored, index, fin)


def disk_rate(directory: Path, nbytes: int) -> float:
    """MB/s of a plain write of nbytes in 1 MiB blocks with fsync (the disk's own rate)."""
    block = np.random.default_rng(0).integers(0, 256, 1 << 20, dtype=np.uint8).tobytes()
    path = directory / "dd.bin"
    t0 = time.perf_counter()
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        left = nbytes
        while left > 0:
            left -= os.write(fd, block[: min(left, len(block))])
        os.fsync(fd)
    finally:
        os.close(fd)
    took = time.perf_counter() - t0
    path.unlink()
    return nbytes / took / 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=2.0, help="seconds of data at the recording's density")
    ap.add_argument("--finalize-seconds", type=float, default=60.0, help="evt_words take timed at finalize")
    ap.add_argument("--dir", type=Path, default=None)
    ap.add_argument("--file", type=Path, default=REAL)
    args = ap.parse_args()
    src = load(args.file)
    print(
        f"{args.file.name}: {src.events} events, {src.words} B of EVT words "
        f"({src.words / src.events:.2f} B/ev), "
        f"{src.span_us} us ({src.events / src.span_us:.2f} Mev/s); decode + chunks "
        f"{src.events / src.decode_s / 1e6:.0f} Mev/s"
    )
    reps = max(1, round(args.seconds * 1e6 / src.span_us))
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        d = Path(tmp)
        one = {s: write(d / f"one-{s}.h5", src, s, 1, finalize=False) for s in ("evt_words", "columns")}
        rows = {s: write(d / f"{s}.h5", src, s, reps, finalize=True) for s in ("evt_words", "columns")}
        mb = max(r.file_bytes for r in rows.values())
        disk = disk_rate(d, mb)
        for p in d.glob("*.h5"):
            p.unlink()
        reps60 = max(1, round(args.finalize_seconds * RATE / src.events))
        fin = write(d / "fin.h5", src, "evt_words", reps60, finalize=True)
    print(
        f"\n{reps} repeats = {rows['evt_words'].events / 1e6:.1f} M events, fsync on; disk {disk:.0f} MB/s\n"
    )
    head = "| storage | B/ev events (one pass) | B/ev index | writer Mev/s | Mev/s CPU | file MB/s "
    head += "| finalize s |"
    print(head)
    print("|---|---|---|---|---|---|---|")
    for s in ("evt_words", "columns"):
        r, o = rows[s], one[s]
        print(
            f"| {s} | {o.stored_bytes / o.events:.2f} | {r.index_bytes / r.events:.3f} | "
            f"{r.events / r.wall_s / 1e6:.1f} | {r.events / r.cpu_s / 1e6:.1f} | "
            f"{r.file_bytes / r.wall_s / 1e6:.0f} | {r.finalize_s:.3f} |"
        )
    print(f"| plain write + fsync, {mb / 1e6:.0f} MB | | | | | {disk:.0f} | |")
    col = rows["columns"]
    print(
        f"\nfinalize, {args.finalize_seconds:.0f} s at 20 Mev/s ({fin.events / 1e6:.0f} M events): evt_words "
        f"{fin.finalize_s:.3f} s; columns {col.finalize_s * fin.events / col.events:.1f} s scaled from "
        f"{col.events / 1e6:.0f} M events ({col.finalize_s:.2f} s)"
    )


if __name__ == "__main__":
    main()
