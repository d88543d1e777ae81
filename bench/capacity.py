"""Capture capacity: the highest load the capture pipeline holds with zero loss, fed by replay.

    python -m bench.capacity [--seconds 5] [--levels 0.3,0.2,0.12,0.08,0.05,0.03]
                             [--rates 30,60,90,120] [--parts events,frames,micro,speed,device]
                             [--runs 2] [--max-lag 1] [--micro-events 8000000] [--repeat 3]
                             [--out DIR] [--keep]

Source takes are recorded on the simulator's virtual clock (cheap, deterministic, nothing lost
to the simulator's own slowness), then each is replayed in real time (`replay://`: the pty
trigger box, the recorded frames, the recorded events re-encoded as EVT 3.0 and decoded by the
production decoder) and captured again by `run_capture`. A level passes when every one of
its `--runs` re-captures lost nothing (no loss record with a count, no device or host buffer
drop, every frame and event of the source in the new take) and kept up (see below).

1. `events`: the default rig (3 x 1280x720 rgb8 @ 30 Hz) at rising event rates (the ideal
   pixels' contrast `threshold`, lower is more events; the rate is measured from the take).
2. `frames`: trigger rates `--rates` at the default event threshold.
3. `micro`: single-threaded throughput of each stage on the densest recorded data (EVT 3.0
   encode and take read: the replay's own cost; EVT 3.0 decode, the writer's event sink into
   HDF5 with the take's LZ4+shuffle and without, in memory and on disk; frame writes) and the
   per-sensor ceiling they imply, against the 20 Mev/s a Prophesee Gen4 sensor can burst to.
4. `speed`: the default rig take replayed on `clock=virtual` (x real time) and in real time.
5. `device` (only when named): device-like sources instead of a replayed take: two `file://`
   sensors handing out the real Gen4.1 EVT 3.0 bytes at `--paces`, cameras whose frames are in
   memory, a burst and an overload level; see `bench.capacity_device` for what it prints.

The replay source runs on the same cores as the capture it feeds (reading and LZ4-decoding the
take, encoding EVT 3.0, pacing the pty trigger box), so a level's verdict is a lower bound on
what the pipeline holds from real devices. A take of a few seconds also fits in what the
buffers absorb (1024 x 5 ms event packets per sensor, 256 writer queue items), so a level that
only buffers would pass a loss check: it must also keep up, its last data written within
`--max-lag` seconds of real time ("lag s"). "max queue" shows how close the writer queue came
to its bound.
"""

from __future__ import annotations

import argparse
import itertools
import logging
import math
import os
import shutil
import statistics
import tempfile
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, cast

import h5py
import numpy as np

from bench.capacity_device import add_device_arguments, device_part_from_args
from drivers.evt import Evt3Encoder, StreamDecoder
from firmware_sim.event_sensor import SLICE_US
from firmware_sim.world import reset_world
from rigd.app.capture import CaptureResult, Progress, run_capture
from rigd.app.config import RigConfig, default_sim_rig
from rigd.app.replay import replay_config
from rigd.core.events import EventArray
from rigd.core.frames import Frame
from rigd.core.layout import EVENT_DTYPES
from rigd.core.settings import WriterConfig
from rigd.take import Take
from rigd.take.h5file import compression_options
from rigd.take.sinks import CameraSink, EventSink

log = logging.getLogger(__name__)

DEFAULT_THRESHOLDS = (0.3, 0.2, 0.12, 0.08, 0.05, 0.03)
DEFAULT_RATES = (30.0, 60.0, 90.0, 120.0)
#: The default sim event sensor's contrast threshold (firmware_sim.event_sensor).
DEFAULT_THRESHOLD = 0.3
#: The paper's rig: two Prophesee Gen4 sensors that can burst above this, each (Mev/s).
TARGET_MEVS = 20.0
#: Device counter names that count something lost (drops, overflows, decoder skips).
_LOSS_WORDS = ("drop", "overflow", "lost", "skipped")
PARTS = ("events", "frames", "micro", "speed", "device")
#: What runs without --parts: the device part is asked for by name (bench.capacity_device).
DEFAULT_PARTS = ("events", "frames", "micro", "speed")


# ----------------------------------------------------------------------------- source takes
@dataclass(slots=True)
class Source:
    """A recorded source take and what it holds."""

    path: Path
    label: str
    threshold: float
    rate_hz: float
    frames: dict[str, int]
    events: dict[str, int]
    window_s: float
    record_wall_s: float
    frame_bytes: int = 0
    """Bytes of one frame of every camera together."""

    @property
    def mevs_per_sensor(self) -> float:
        if not self.events or not self.window_s:
            return 0.0
        return sum(self.events.values()) / len(self.events) / self.window_s / 1e6

    @property
    def fps_total(self) -> float:
        return sum(self.frames.values()) / self.window_s if self.window_s else 0.0

    @property
    def frame_mbs(self) -> float:
        """Frame payload the cameras deliver, MB/s (all cameras)."""
        return self.frame_bytes * self.fps_total / len(self.frames) / 1e6 if self.frames else 0.0


def take_counts(path: Path) -> tuple[dict[str, int], dict[str, int], int]:
    """Frames per camera and events per sensor a take holds, and the bytes of one frame of
    every camera together."""
    with Take(path) as take:
        return (
            {c: len(take.frames(c)) for c in take.cameras},
            {s: take.sensor(s).count for s in take.event_sensors},
            sum(int(np.prod(take.frames(c, demosaic=False).stored_shape)) for c in take.cameras),
        )


def sim_rig(threshold: float, rate_hz: float, seed: int) -> tuple[RigConfig, str]:
    """The default sim rig on the virtual clock, its event sensors at `threshold`."""
    world = f"capacity-{uuid.uuid4().hex[:8]}"
    cfg = default_sim_rig(world=world, seed=seed, rate_hz=rate_hz, clock="virtual")
    for sensor in cfg.event_sensors:
        sensor.spec += f"&threshold={threshold:g}"
    return cfg, world


def record_source(
    out_dir: Path, *, threshold: float, rate_hz: float, seconds: float, seed: int = 0
) -> Source:
    """Record a source take on the virtual clock."""
    cfg, world = sim_rig(threshold, rate_hz, seed)
    label = f"thr {threshold:g} @ {rate_hz:g} Hz"
    log.info("recording source %s, %.1f s (virtual clock)", label, seconds)
    t0 = time.perf_counter()
    try:
        res = run_capture(cfg, out_dir, seconds)
    finally:
        reset_world(world)
    wall = time.perf_counter() - t0
    # The source's gigabytes go to disk now, not during the replay it is measured by.
    os.sync()
    lost = [r for r in res.report.losses if r.count]
    if lost:
        log.warning("source %s itself lost data: %s", label, lost)
    frames, events, frame_bytes = take_counts(res.path)
    src = Source(
        res.path, label, threshold, rate_hz, frames, events, res.window_s or seconds, wall, frame_bytes
    )
    log.info(
        "source %s: %.2f Mev/s per sensor, %.0f frames/s, recorded in %.1f s",
        label,
        src.mevs_per_sensor,
        src.fps_total,
        wall,
    )
    return src


# ----------------------------------------------------------------------------- replay levels
@dataclass(slots=True)
class Level:
    """One replayed and re-captured source take, judged."""

    source: Source
    clock: str
    result: CaptureResult
    wall_s: float
    max_queue: int
    queue_capacity: int
    missing_events: int
    missing_frames: int
    lost_events: int
    lost_frames: int
    drops: dict[str, int] = field(default_factory=dict)
    zero_count_records: int = 0
    data_s: float | None = None
    """From the first pulse record to the last frame or event written."""
    max_lag_s: float = math.inf
    """The most `lag_s` a passing level may show (it kept up, not only buffered)."""

    @property
    def lag_s(self) -> float | None:
        """How far behind real time the last data was written (data_s - recorded span)."""
        return None if self.data_s is None else self.data_s - self.source.window_s

    @property
    def lossless(self) -> bool:
        return not (
            self.missing_events or self.missing_frames or self.lost_events or self.lost_frames or self.drops
        )

    @property
    def kept_up(self) -> bool:
        return self.lag_s is not None and self.lag_s <= self.max_lag_s

    @property
    def passed(self) -> bool:
        return self.lossless and self.kept_up

    def verdict(self) -> str:
        if self.passed:
            return "pass"
        why = []
        if self.missing_events or self.missing_frames:
            why.append("missing")
        if self.lost_events or self.lost_frames:
            why.append("losses")
        if self.drops:
            why.append("drops")
        if not self.kept_up:
            why.append("lag")
        return "FAIL (" + ", ".join(why) + ")"


def device_drops(counters: dict[str, dict[str, int]]) -> dict[str, int]:
    """Non-zero loss counters per `device.counter` (device, transport, host buffer, decoder)."""
    out: dict[str, int] = {}
    for dev, cnt in counters.items():
        for key, value in cnt.items():
            if value and any(w in key for w in _LOSS_WORDS):
                out[f"{dev}.{key}"] = int(value)
    return out


def replay_capture(
    source: Source,
    out_dir: Path,
    clock: Literal["real", "virtual"] = "real",
    *,
    keep: bool = False,
    max_lag_s: float = math.inf,
) -> Level:
    """Replay a source take through the real drivers and capture it again; judge the result."""
    cfg, duration = replay_config(source.path, clock=clock)
    peak = [0]
    marks: dict[str, float] = {}

    def on_progress(p: Progress) -> None:
        now = time.perf_counter()
        peak[0] = max(peak[0], p.queue_depth)
        if p.pulses and "first" not in marks:
            marks["first"] = now
        written = sum(p.frames.values()) + sum(p.events.values())
        if written > marks.get("written", 0):
            marks["written"], marks["last"] = written, now

    log.info("replaying %s on the %s clock (%.1f s recorded)", source.label, clock, duration)
    t0 = time.perf_counter()
    try:
        res = run_capture(cfg, out_dir, duration, on_progress=on_progress)
    finally:
        reset_world(f"replay:{source.path.resolve()}")
    wall = time.perf_counter() - t0
    records = res.report.losses
    lost_ev = sum(r.count for r in records if r.what == "events")
    lost_fr = sum(r.count for r in records if r.what == "frames")
    missing_ev = sum(max(0, n - res.events.get(s, 0)) for s, n in source.events.items())
    missing_fr = sum(max(0, n - res.frames.get(c, 0)) for c, n in source.frames.items())
    level = Level(
        source=source,
        clock=clock,
        result=res,
        wall_s=wall,
        max_queue=peak[0],
        queue_capacity=cfg.writer.queue_items,
        missing_events=missing_ev,
        missing_frames=missing_fr,
        lost_events=lost_ev,
        lost_frames=lost_fr,
        drops=device_drops(res.report.device_counters),
        zero_count_records=sum(1 for r in records if not r.count),
        data_s=marks["last"] - marks["first"] if "last" in marks and "first" in marks else None,
        max_lag_s=max_lag_s,
    )
    log.info(
        "%s: %s; missing %d events %d frames; losses recorded %d events %d frames; drops %s; "
        "max queue %d; lag %s s; wall %.1f s",
        source.label,
        level.verdict(),
        missing_ev,
        missing_fr,
        lost_ev,
        lost_fr,
        level.drops or "none",
        level.max_queue,
        "-" if level.lag_s is None else f"{level.lag_s:.2f}",
        wall,
    )
    if not keep:
        res.path.unlink(missing_ok=True)
    return level


def _num(v: float | None, width: int, digits: int) -> str:
    return f"{'-':>{width}}" if v is None else f"{v:>{width}.{digits}f}"


def worst(runs: Sequence[Level]) -> Level:
    """The run a level is judged by: the first that failed, else the one furthest behind."""
    failed = [lv for lv in runs if not lv.passed]
    return failed[0] if failed else max(runs, key=lambda lv: lv.lag_s or 0.0)


def level_table(title: str, key: str, levels: Sequence[Sequence[Level]]) -> list[str]:
    """The pass/fail table of one sweep (each level: its replays, judged by the worst), and
    the highest passing level."""
    lines = [title]
    lines.append(
        f"{key:<10}{'src s':>6}{'Mev/s/sensor':>13}{'frames/s':>10}{'MB/s frames':>12}{'lost ev':>12}"
        f"{'lost fr':>9}{'max queue':>11}{'lag s':>7}{'wall s':>8}{'runs':>6}  result"
    )
    for runs in levels:
        lv = worst(runs)
        s = lv.source
        name = f"{s.threshold:g}" if key == "threshold" else f"{s.rate_hz:g} Hz"
        lost_ev = max(lv.missing_events, lv.lost_events)
        lost_fr = max(lv.missing_frames, lv.lost_frames)
        queue = f"{lv.max_queue}/{lv.queue_capacity}"
        n_ok = f"{sum(r.passed for r in runs)}/{len(runs)}"
        lines.append(
            f"{name:<10}{s.window_s:>6.2f}{s.mevs_per_sensor:>13.2f}{s.fps_total:>10.1f}{s.frame_mbs:>12.0f}"
            f"{lost_ev:>12,d}{lost_fr:>9,d}{queue:>11}{_num(lv.lag_s, 7, 2)}{lv.wall_s:>8.1f}{n_ok:>6}"
            f"  {lv.verdict()}"
        )
        if lv.drops:
            lines.append(f"{'':<10}drops: {lv.drops}")
    passing = [runs[0].source for runs in levels if all(r.passed for r in runs)]
    if passing:
        best = max(passing, key=lambda src: (src.mevs_per_sensor, src.fps_total))
        lines.append(
            f"highest passing: {best.label}: {best.mevs_per_sensor:.2f} Mev/s per sensor, "
            f"{best.fps_total:.0f} frames/s"
        )
    else:
        lines.append("highest passing: none")
    return lines


def replay_runs(source: Source, out_dir: Path, runs: int, *, keep: bool, max_lag_s: float) -> list[Level]:
    """Up to `runs` real-time replays of a source; stops at the first that fails."""
    out: list[Level] = []
    for _ in range(runs):
        out.append(replay_capture(source, out_dir, keep=keep, max_lag_s=max_lag_s))
        if not out[-1].passed:
            break
    return out


# ----------------------------------------------------------------------------- microbenchmarks
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
    """The production decoder, fed buffer by buffer as `EvtStreamSensor` feeds it."""
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
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        path.unlink()
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
    source: Source, tmp: Path, *, n_events: int, repeat: int, n_frames: int = 120
) -> MicroResult:
    """Every stage on the source take's data (first `n_events` of its first sensor)."""
    with Take(source.path) as take:
        sensor = take.event_sensors[0]
        width, height = take.sensor(sensor).geometry
        n = min(n_events, take.sensor(sensor).count)
        read_times = timed(lambda: take.sensor(sensor).by_index(0, n), repeat)
        events = take.sensor(sensor).by_index(0, n)
        cam = take.frames(take.cameras[0], demosaic=False)  # frames as stored: the writer's input
        k = min(30, len(cam))
        frame_read = timed(lambda: [cam[i] for i in range(k)], repeat)
        frames = [cam[i] for i in range(k)]
    log.info("microbenchmarks on %s: %d events of %s, %d frames", source.label, n, sensor, len(frames))
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


def ceiling_table(micro: MicroResult, frame_mbs: float, measured: Level | None) -> list[str]:
    """Per-stage rates and the per-sensor ceiling they imply (two sensors), against 20 Mev/s."""
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
    if measured is not None:
        m = measured.source.mevs_per_sensor
        lines.append(row("measured: highest passing replay level (replay on same cores)", m, 2))
    return lines


# ----------------------------------------------------------------------------- replay speed
def speed_table(levels: Sequence[Level]) -> list[str]:
    """x real time: the span the re-capture holds / seconds from its first pulse record to the
    last data written ("data"), and / the whole run (opening the devices to the sealed take)."""
    lines = [
        f"{'clock':<9}{'recorded s':>11}{'captured s':>11}{'data s':>8}{'wall s':>8}{'x real (data)':>15}"
        f"{'x real (wall)':>15}  lossless",
    ]
    for lv in levels:
        rec = lv.source.window_s
        got = lv.result.window_s or 0.0
        data = lv.data_s
        ratio = None if not data else got / data
        lines.append(
            f"{lv.clock:<9}{rec:>11.2f}{got:>11.2f}{_num(data, 8, 2)}{lv.wall_s:>8.2f}{_num(ratio, 15, 2)}"
            f"{got / lv.wall_s:>15.2f}  {'yes' if lv.lossless else 'no: ' + lv.verdict()}"
        )
    return lines


# ----------------------------------------------------------------------------- main
def _floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v.strip()]


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=5.0, help="length of each source take")
    ap.add_argument(
        "--levels",
        type=_floats,
        default=list(DEFAULT_THRESHOLDS),
        help="event thresholds, comma-separated (lower: more events)",
    )
    ap.add_argument("--rates", type=_floats, default=list(DEFAULT_RATES), help="trigger rates, Hz")
    ap.add_argument("--parts", default=",".join(DEFAULT_PARTS), help=f"which of {','.join(PARTS)} to run")
    ap.add_argument("--runs", type=int, default=2, help="real-time replays per level (all must pass)")
    ap.add_argument(
        "--max-lag",
        type=float,
        default=1.0,
        help="seconds behind real time the last data may land and the level still pass: a "
        "pipeline that keeps up lands it within ~0.5 s (1 s flushes); one that does not, only "
        "buffers, and a longer take turns that lag into loss",
    )
    ap.add_argument("--micro-events", type=int, default=8_000_000, help="events for the microbenchmarks")
    ap.add_argument("--repeat", type=int, default=3, help="runs per microbenchmark (median reported)")
    ap.add_argument("--out", type=Path, default=None, help="directory on the disk to measure (default: tmp)")
    ap.add_argument("--keep", action="store_true", help="keep the takes (printed)")
    add_device_arguments(ap)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    log.setLevel(logging.INFO)
    parts = {p.strip() for p in args.parts.split(",") if p.strip()}
    unknown = parts - set(PARTS)
    if unknown:
        ap.error(f"unknown part(s) {sorted(unknown)}; use {','.join(PARTS)}")

    load0 = os.getloadavg()
    t_start = time.perf_counter()
    root = Path(tempfile.mkdtemp(prefix="rigd-capacity-", dir=args.out))
    src_dir, cap_dir = root / "src", root / "cap"
    src_dir.mkdir()
    cap_dir.mkdir()
    out: list[str] = []
    default: Source | None = None
    densest: Source | None = None
    best_event_level: Level | None = None
    try:
        if parts - {"device"}:
            # Warm-up, not reported: numba compiles its kernels and the page cache fills on the
            # first replay, which would otherwise count against the first level.
            warm = record_source(src_dir, threshold=DEFAULT_THRESHOLD, rate_hz=30.0, seconds=1.0)
            replay_capture(warm, cap_dir)
            warm.path.unlink(missing_ok=True)
        if "events" in parts:
            levels: list[list[Level]] = []
            for thr in args.levels:
                src = record_source(src_dir, threshold=thr, rate_hz=30.0, seconds=args.seconds)
                levels.append(replay_runs(src, cap_dir, args.runs, keep=args.keep, max_lag_s=args.max_lag))
                if thr == DEFAULT_THRESHOLD and default is None:
                    default = src
                if densest is None or src.mevs_per_sensor > densest.mevs_per_sensor:
                    if densest is not None and densest is not default and not args.keep:
                        densest.path.unlink(missing_ok=True)
                    densest = src
                elif src is not default and not args.keep:
                    src.path.unlink(missing_ok=True)
            passing = [runs[0] for runs in levels if all(r.passed for r in runs)]
            best_event_level = max(passing, key=lambda lv: lv.source.mevs_per_sensor) if passing else None
            out += level_table(
                f"1. event rate per sensor, 3 x 720p rgb8 @ 30 Hz beside it ({args.seconds:g} s takes, "
                "real-time replay)",
                "threshold",
                levels,
            )
            out.append("")
        if "frames" in parts:
            levels = []
            for rate in args.rates:
                if rate == 30.0 and default is not None:
                    src = default
                else:
                    src = record_source(
                        src_dir, threshold=DEFAULT_THRESHOLD, rate_hz=rate, seconds=args.seconds
                    )
                levels.append(replay_runs(src, cap_dir, args.runs, keep=args.keep, max_lag_s=args.max_lag))
                if rate == 30.0 and default is None:
                    default = src
                elif src is not default and src is not densest and not args.keep:
                    src.path.unlink(missing_ok=True)
            out += level_table(
                f"2. trigger rate, event sensors at the default threshold {DEFAULT_THRESHOLD:g} beside it "
                f"({args.seconds:g} s takes, real-time replay)",
                "rate",
                levels,
            )
            out.append("")
        if "micro" in parts:
            micro_src = densest or default
            if micro_src is None:
                micro_src = default = record_source(
                    src_dir, threshold=DEFAULT_THRESHOLD, rate_hz=30.0, seconds=args.seconds
                )
            micro = micro_benchmarks(micro_src, root, n_events=args.micro_events, repeat=args.repeat)
            frame_mbs = default.frame_mbs if default is not None else 3 * 30 * micro.frame_mb
            out.append(f"3. where the time goes (data: {micro_src.label}, sensor 0)")
            out += ceiling_table(micro, frame_mbs, best_event_level)
            out.append("")
        if "speed" in parts:
            if default is None:
                default = record_source(
                    src_dir, threshold=DEFAULT_THRESHOLD, rate_hz=30.0, seconds=args.seconds
                )
            speed = [replay_capture(default, cap_dir, "virtual"), replay_capture(default, cap_dir, "real")]
            out.append(
                f"4. replay speed, default rig take ({default.label}, "
                f"{default.mevs_per_sensor:.2f} Mev/s/sensor)"
            )
            out += speed_table(speed)
            out.append("")
        if "device" in parts:
            out += device_part_from_args(ap, args, cap_dir)
            out.append("")
    finally:
        if args.keep:
            log.info("takes kept in %s", root)
        else:
            shutil.rmtree(root, ignore_errors=True)
    load1 = os.getloadavg()
    out.append(
        f"{os.cpu_count()} cores; load average before {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}, "
        f"after {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}; whole run {time.perf_counter() - t_start:.0f} s"
    )
    print("\n".join(out))


if __name__ == "__main__":
    main()
