"""`python -m bench.capacity`'s part 3, `micro`: single-threaded throughput of each stage on
recorded events and frames (EVT 3.0 encode and take read, the replay's own cost; EVT 3.0
decode, the writer's event sink with and without HDF5 and compression, in memory and on disk;
frame writes) and the per-sensor ceiling they imply, against what a Prophesee Gen4 sensor can
burst to."""

from __future__ import annotations

import itertools
import logging
import math
import os
import statistics
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import h5py
import numpy as np

from firmware_sim.event_sensor import SLICE_US
from rigd.core.events import EventArray
from rigd.core.frames import Frame
from rigd.core.layout import EVENT_DTYPES
from rigd.core.settings import WriterConfig
from rigd.evt import Evt3Encoder, StreamDecoder
from rigd.take import Take
from rigd.take.h5file import compression_options
from rigd.take.sinks import CameraSink, EventSink

log = logging.getLogger(__name__)

#: The paper's rig: two Prophesee Gen4 sensors that can burst above this, each (Mev/s).
TARGET_MEVS = 20.0


@dataclass(slots=True)
class Stage:
    name: str
    side: str
    """"source" (the replay's own cost) or "capture" (the pipeline's)."""
    unit: str
    """"Mev/s" or "MB/s"."""
    median: float
    best: float
    note: str = ""


def timed(fn: Callable[[], Any], repeat: int) -> list[float]:
    """Wall seconds of `repeat` calls (after one warm-up call: compilation, page cache)."""
    fn()
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def rate_stage(name: str, side: str, amount: float, times: list[float], unit: str, note: str = "") -> Stage:
    """A stage's rate from the amount (events, or MB) processed per call."""
    return Stage(name, side, unit, amount / statistics.median(times), amount / min(times), note)


def slices(events: EventArray, slice_us: int = SLICE_US) -> list[EventArray]:
    """Events cut into `slice_us` spans, as the replay (and the sim sensor) packetises them."""
    t = events.t
    if len(t) == 0:
        return []
    edges = np.arange(int(t[0]), int(t[-1]) + slice_us + 1, slice_us)
    idx = np.searchsorted(t, edges, side="left")
    return [events[int(a) : int(b)] for a, b in itertools.pairwise(idx) if b > a]


def encode_slices(parts: Sequence[EventArray]) -> list[bytes]:
    """One EVT 3.0 stream, one buffer per slice (the replay's encoding)."""
    enc = Evt3Encoder()
    return [enc.encode(p) for p in parts]


def decode_buffers(buffers: Sequence[bytes], width: int, height: int) -> list[EventArray]:
    """The production decoder, fed buffer by buffer as `DecodingEventSensor` feeds it."""
    dec = StreamDecoder("evt3", width=width, height=height)
    return [dec.feed(b).events for b in buffers]


class NullDataset:
    """Stands in for an h5py dataset: takes the writes and stores nothing (the sink's own work
    without HDF5)."""

    def __init__(self) -> None:
        self.shape: tuple[int, ...] = (0,)

    def resize(self, shape: tuple[int, ...]) -> None:
        self.shape = shape

    def __setitem__(self, key: Any, value: Any) -> None:
        pass


def sink_no_hdf5(batches: Sequence[EventArray], width: int, height: int, chunk: int) -> None:
    """The writer's event sink with its datasets stubbed out: batch checks, buffering,
    concatenation and column preparation only."""
    ds: dict[str, Any] = {k: NullDataset() for k in EVENT_DTYPES}
    sink = EventSink("ev0", cast(Any, None), width, height, ds, {}, chunk)
    where = Path("bench")
    for b in batches:
        sink.add_events(b, where)
    sink.write_events(whole_chunks_only=False)


def sink_append(
    batches: Sequence[EventArray],
    width: int,
    height: int,
    opts: dict[str, Any],
    path: Path | None,
    chunk: int,
) -> int:
    """The writer's event sink: batches -> one sensor's datasets; in memory when `path` is None,
    else on disk, closed and fsynced. Returns the bytes stored."""
    # in memory: grow the file image in 4 MiB steps (fewest reallocations, no large memsets)
    kw: dict[str, Any] = (
        {"driver": "core", "backing_store": False, "block_size": 4 << 20} if path is None else {}
    )
    target = path if path is not None else Path(f"capacity-{uuid.uuid4().hex}.h5")
    with h5py.File(target, "w", **kw) as f:
        g = f.create_group("events").create_group("ev0")
        sink = EventSink.create("ev0", g, width, height, chunk, opts)
        for b in batches:
            sink.add_events(b, target)
        sink.write_events(whole_chunks_only=False)
        f.flush()
        stored = sum(int(ds.id.get_storage_size()) for ds in sink.ds.values())
    if path is not None:
        _sync_and_remove(path)
    return stored


def frame_writes(frames: Sequence[Frame], n: int, opts: dict[str, Any], path: Path) -> None:
    """The writer's camera sink: `n` frames (cycling `frames`) to disk, closed and fsynced."""
    with h5py.File(path, "w") as f:
        g = f.create_group("frames").create_group("cam0")
        img = frames[0].image
        fmt = frames[0].pixel_format or ("rgb8" if img.ndim == 3 else "mono8")
        sink = CameraSink.create("cam0", g, tuple(img.shape), np.dtype(img.dtype), opts, fmt)
        for i in range(n):
            fr = frames[i % len(frames)]
            sink.add_frame(
                Frame(fr.image, fr.t_exposure_start_us + i, fr.exposure_us, i, fr.host_time_ns, i), path
            )
        sink.write_series()
        sink.trim_images()
    _sync_and_remove(path)


def _sync_and_remove(path: Path) -> None:
    """What a take on disk costs includes getting it there: fsync, then the file goes."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    path.unlink()


@dataclass(slots=True)
class MicroResult:
    stages: list[Stage]
    n_events: int
    bytes_per_event: float
    lz4_ratio: float
    frame_mb: float


def micro_events(
    events: EventArray, width: int, height: int, tmp: Path, *, repeat: int, chunk: int | None = None
) -> tuple[list[Stage], float, float]:
    """Event stages on `events` (time-ordered, one sensor). Returns the stages, EVT 3.0 bytes
    per event, and the LZ4+shuffle size ratio of the stored columns."""
    n = len(events)
    chunk = chunk or WriterConfig().event_chunk
    events = events.with_time(events.t - int(events.t[0]))
    parts = slices(events)
    buffers = encode_slices(parts)
    size = sum(len(b) for b in buffers)
    decoded = decode_buffers(buffers, width, height)
    got = sum(len(d) for d in decoded)
    if got != n:
        log.warning("EVT 3.0 round trip: %d events decoded of %d", got, n)
    lz4 = compression_options(WriterConfig().event_compression, shuffle=True)
    none = compression_options("none", shuffle=False)
    mev = n / 1e6
    dec_times = timed(lambda: decode_buffers(buffers, width, height), repeat)
    stages = [
        rate_stage(
            "EVT3 encode (5 ms slices)", "source", mev, timed(lambda: encode_slices(parts), repeat), "Mev/s"
        ),
        rate_stage(
            "EVT3 decode, StreamDecoder.feed per 5 ms buffer",
            "capture",
            mev,
            dec_times,
            "Mev/s",
            f"{size / n:.2f} B/event, {size / 1e6 / statistics.median(dec_times):.0f} MB/s in",
        ),
    ]
    stored: dict[str, int] = {}

    def run(key: str, opts: dict[str, Any], disk: bool) -> None:
        path = tmp / f"sink-{key}.h5" if disk else None
        stored[key] = sink_append(decoded, width, height, opts, path, chunk)

    bare = timed(lambda: sink_no_hdf5(decoded, width, height, chunk), repeat)
    mem_lz4 = timed(lambda: run("lz4", lz4, False), repeat)
    mem_none = timed(lambda: run("none", none, False), repeat)
    disk_lz4 = timed(lambda: run("lz4-disk", lz4, True), repeat)
    disk_none = timed(lambda: run("none-disk", none, True), repeat)
    stages += [
        rate_stage("EventSink checks + buffering, HDF5 stubbed", "capture", mev, bare, "Mev/s"),
        rate_stage("EventSink append, LZ4+shuffle, in memory", "capture", mev, mem_lz4, "Mev/s"),
        rate_stage("EventSink append, uncompressed, in memory", "capture", mev, mem_none, "Mev/s"),
    ]
    # the LZ4 + shuffle filter alone: what the compressed in-memory append costs over the plain
    # one (left out when within the noise)
    comp = statistics.median(mem_lz4) - statistics.median(mem_none)
    if comp > 0.05 * statistics.median(mem_lz4):
        stages.append(
            Stage("LZ4+shuffle filter alone (difference)", "capture", "Mev/s", mev / comp, math.nan)
        )
    else:
        log.info("LZ4+shuffle in memory costs no more than the plain append here (within 5 %%)")
    stages += [
        rate_stage("EventSink append, LZ4+shuffle, disk+fsync", "capture", mev, disk_lz4, "Mev/s"),
        rate_stage("EventSink append, uncompressed, disk+fsync", "capture", mev, disk_none, "Mev/s"),
    ]
    ratio = stored["lz4"] / max(1, stored["none"])
    return stages, size / n, ratio


def micro_benchmarks(
    path: Path, label: str, tmp: Path, *, n_events: int, repeat: int, n_frames: int = 120
) -> MicroResult:
    """Every stage on a source take's data (first `n_events` of its first sensor)."""
    with Take(path) as take:
        sensor = take.event_sensors[0]
        width, height = take.sensor(sensor).geometry
        n = min(n_events, take.sensor(sensor).count)
        read_times = timed(lambda: take.sensor(sensor).by_index(0, n), repeat)
        events = take.sensor(sensor).by_index(0, n)
        cam = take.camera(take.cameras[0], demosaic=False)  # frames as stored: the writer's input
        k = min(30, len(cam))
        frame_read = timed(lambda: [cam[i] for i in range(k)], repeat)
        frames = [cam[i] for i in range(k)]
    log.info("microbenchmarks on %s: %d events of %s, %d frames", label, n, sensor, len(frames))
    stages = [rate_stage("take read, events (LZ4 decompress)", "source", n / 1e6, read_times, "Mev/s")]
    ev_stages, bpe, ratio = micro_events(events, width, height, tmp, repeat=repeat)
    stages += ev_stages
    frame_mb = frames[0].image.nbytes / 1e6
    stages.append(rate_stage("take read, frames", "source", k * frame_mb, frame_read, "MB/s"))
    opts = compression_options(WriterConfig().frame_compression, shuffle=False)
    ft = timed(lambda: frame_writes(frames, n_frames, opts, tmp / "frames.h5"), repeat)
    stages.append(
        rate_stage(
            f"CameraSink frame writes, disk+fsync ({frame_mb:.2f} MB frames)",
            "capture",
            n_frames * frame_mb,
            ft,
            "MB/s",
        )
    )
    return MicroResult(stages, n, bpe, ratio, frame_mb)


def ceiling_table(micro: MicroResult, frame_mbs: float, measured_mevs: float | None) -> list[str]:
    """Per-stage rates and the per-sensor ceiling they imply (two sensors), against 20 Mev/s;
    `measured_mevs`: per sensor, the highest replay level that passed, if one was run."""
    st = {s.name: s for s in micro.stages}

    def find(prefix: str) -> Stage:
        return next(s for n, s in st.items() if n.startswith(prefix))

    lines = [
        f"stages, single-threaded, median of runs ({micro.n_events / 1e6:.1f} M events; "
        f"EVT 3.0 {micro.bytes_per_event:.2f} B/event; LZ4+shuffle stores {micro.lz4_ratio:.2f} of raw)",
        f"{'stage':<52}{'side':>8}{'median':>10}{'best':>10}{'unit':>7}{'per sensor':>12}{'of 20':>7}",
    ]
    for s in micro.stages:
        if s.unit == "Mev/s":
            per = s.median / 2
            best = "-" if math.isnan(s.best) else f"{s.best:.1f}"
            lines.append(
                f"{s.name:<52}{s.side:>8}{s.median:>10.1f}{best:>10}{s.unit:>7}{per:>12.1f}"
                f"{per / TARGET_MEVS:>7.2f}"
            )
        else:
            lines.append(f"{s.name:<52}{s.side:>8}{s.median:>10.0f}{s.best:>10.0f}{s.unit:>7}{'':>12}{'':>7}")
    dec = find("EVT3 decode").median
    app = find("EventSink append, LZ4+shuffle, disk").median
    frames = find("CameraSink").median
    busy = frame_mbs / frames
    left = max(0.0, 1.0 - busy)
    writer = left * app / 2
    one_core = left / (1 / dec + 1 / app) / 2
    two_cores = min(dec / 2, writer)
    # this bench's replay source on the same core: reading the take (events, frames) and encoding
    src_busy = busy + frame_mbs / find("take read, frames").median
    src_left = max(0.0, 1.0 - src_busy)
    per_event = sum(1 / find(p).median for p in ("take read, events", "EVT3 encode", "EVT3 decode"))
    with_source = src_left / (per_event + 1 / app) / 2
    lines += [
        "(per sensor: the stage's rate shared by two sensors on one core; of 20: per sensor / 20 Mev/s)",
        f"frames {frame_mbs:.0f} MB/s take {busy * 100:.0f} % of the writer thread "
        f"(CameraSink at {frames:.0f} MB/s)",
        f"{'implied ceiling, per sensor, two sensors + the frames':<60}{'Mev/s':>8}{'of 20':>7}",
    ]

    def row(label: str, v: float, digits: int = 1) -> str:
        return f"{label:<60}{v:>8.{digits}f}{v / TARGET_MEVS:>7.2f}"

    lines += [
        row("writer thread alone (LZ4 append to disk, after frames)", writer),
        row("decode + writer on one core", one_core),
        row("decode on one core, writer on the other", two_cores),
        row("replay source + decode + writer on one core", with_source),
    ]
    if measured_mevs is not None:
        lines.append(row("measured: highest passing replay level (replay on same cores)", measured_mevs, 2))
    return lines
