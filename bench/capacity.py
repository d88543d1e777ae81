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
import logging
import math
import os
import shutil
import tempfile
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from bench.capacity_device import add_device_arguments, device_part_from_args
from bench.capacity_micro import ceiling_table, micro_benchmarks
from bench.capacity_micro import log as micro_log
from firmware_sim.world import reset_world
from rigd.app.capture import CaptureResult, Progress, run_capture
from rigd.app.config import RigConfig, default_sim_rig
from rigd.app.replay import replay_config
from rigd.take import Take

log = logging.getLogger(__name__)

DEFAULT_THRESHOLDS = (0.3, 0.2, 0.12, 0.08, 0.05, 0.03)
DEFAULT_RATES = (30.0, 60.0, 90.0, 120.0)
#: The default sim event sensor's contrast threshold (firmware_sim.event_sensor).
DEFAULT_THRESHOLD = 0.3
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
            {c: len(take.camera(c)) for c in take.cameras},
            {s: take.sensor(s).count for s in take.event_sensors},
            sum(int(np.prod(take.camera(c, demosaic=False).stored_shape)) for c in take.cameras),
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


def _parser() -> argparse.ArgumentParser:
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
    return ap


@dataclass(slots=True)
class _Run:
    """What the parts of one run share: the arguments, where takes go, and the source takes a
    later part reuses instead of recording again (the default rig's, the densest)."""

    args: argparse.Namespace
    src_dir: Path
    cap_dir: Path
    default: Source | None = None
    """The default rig's take: threshold DEFAULT_THRESHOLD at 30 Hz."""
    densest: Source | None = None
    """The take with the most events per sensor so far (the microbenchmarks' data)."""
    best_event_level: Level | None = None
    """The highest passing event-rate level (the ceiling table's measured row)."""

    def record(self, threshold: float = DEFAULT_THRESHOLD, rate_hz: float = 30.0) -> Source:
        return record_source(self.src_dir, threshold=threshold, rate_hz=rate_hz, seconds=self.args.seconds)

    def replay(self, source: Source) -> list[Level]:
        a = self.args
        return replay_runs(source, self.cap_dir, a.runs, keep=a.keep, max_lag_s=a.max_lag)

    def drop(self, source: Source) -> None:
        """Delete a source take no later part reuses (unless --keep)."""
        if source is not self.default and source is not self.densest and not self.args.keep:
            source.path.unlink(missing_ok=True)


def _warm_up(run: _Run) -> None:
    """Not reported: numba compiles its kernels and the page cache fills on the first replay,
    which would otherwise count against the first level."""
    warm = record_source(run.src_dir, threshold=DEFAULT_THRESHOLD, rate_hz=30.0, seconds=1.0)
    replay_capture(warm, run.cap_dir)
    warm.path.unlink(missing_ok=True)


def _events_part(run: _Run) -> list[str]:
    """1. Rising event rates beside the default cameras; keeps the default and densest takes."""
    levels: list[list[Level]] = []
    for thr in run.args.levels:
        src = run.record(threshold=thr)
        levels.append(run.replay(src))
        if thr == DEFAULT_THRESHOLD and run.default is None:
            run.default = src
        if run.densest is None or src.mevs_per_sensor > run.densest.mevs_per_sensor:
            previous, run.densest = run.densest, src
            if previous is not None:
                run.drop(previous)
        else:
            run.drop(src)
    passing = [runs[0] for runs in levels if all(r.passed for r in runs)]
    run.best_event_level = max(passing, key=lambda lv: lv.source.mevs_per_sensor) if passing else None
    return level_table(
        f"1. event rate per sensor, 3 x 720p rgb8 @ 30 Hz beside it ({run.args.seconds:g} s takes, "
        "real-time replay)",
        "threshold",
        levels,
    )


def _frames_part(run: _Run) -> list[str]:
    """2. Rising trigger rates at the default event threshold (30 Hz: the default take)."""
    levels: list[list[Level]] = []
    for rate in run.args.rates:
        src = run.default if rate == 30.0 and run.default is not None else run.record(rate_hz=rate)
        levels.append(run.replay(src))
        if rate == 30.0 and run.default is None:
            run.default = src
        else:
            run.drop(src)
    return level_table(
        f"2. trigger rate, event sensors at the default threshold {DEFAULT_THRESHOLD:g} beside it "
        f"({run.args.seconds:g} s takes, real-time replay)",
        "rate",
        levels,
    )


def _micro_part(run: _Run, tmp: Path) -> list[str]:
    """3. Where the time goes, on the densest take recorded (else the default rig's)."""
    src = run.densest or run.default
    if src is None:
        src = run.default = run.record()
    micro = micro_benchmarks(src.path, src.label, tmp, n_events=run.args.micro_events, repeat=run.args.repeat)
    frame_mbs = run.default.frame_mbs if run.default is not None else 3 * 30 * micro.frame_mb
    best = run.best_event_level
    return [
        f"3. where the time goes (data: {src.label}, sensor 0)",
        *ceiling_table(micro, frame_mbs, None if best is None else best.source.mevs_per_sensor),
    ]


def _speed_part(run: _Run) -> list[str]:
    """4. The default rig's take replayed on the virtual clock and in real time."""
    if run.default is None:
        run.default = run.record()
    src = run.default
    speed = [replay_capture(src, run.cap_dir, "virtual"), replay_capture(src, run.cap_dir, "real")]
    return [
        f"4. replay speed, default rig take ({src.label}, {src.mevs_per_sensor:.2f} Mev/s/sensor)",
        *speed_table(speed),
    ]


def main(argv: Sequence[str] | None = None) -> None:
    ap = _parser()
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    log.setLevel(logging.INFO)
    micro_log.setLevel(logging.INFO)
    parts = {p.strip() for p in args.parts.split(",") if p.strip()}
    unknown = parts - set(PARTS)
    if unknown:
        ap.error(f"unknown part(s) {sorted(unknown)}; use {','.join(PARTS)}")

    load0 = os.getloadavg()
    t_start = time.perf_counter()
    root = Path(tempfile.mkdtemp(prefix="rigd-capacity-", dir=args.out))
    run = _Run(args, root / "src", root / "cap")
    run.src_dir.mkdir()
    run.cap_dir.mkdir()
    steps: list[tuple[str, Callable[[], list[str]]]] = [
        ("events", lambda: _events_part(run)),
        ("frames", lambda: _frames_part(run)),
        ("micro", lambda: _micro_part(run, root)),
        ("speed", lambda: _speed_part(run)),
        ("device", lambda: device_part_from_args(ap, args, run.cap_dir)),
    ]
    out: list[str] = []
    try:
        if parts - {"device"}:
            _warm_up(run)
        for name, part in steps:
            if name in parts:
                out += [*part(), ""]
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
