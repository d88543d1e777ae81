"""Reconstruction of takes for 4D training: denoise, one rig-level segmentation, keyframes, snapshots.

Per take, in three phases of independent tasks (`reconstruct_tasks`), each reading one bounded
block of events, so memory does not grow with the take and the work spreads over every worker:

1. **scan**: every block of every event sensor is filtered (background-activity filter) and its
   kept events are counted in `partition_window_us` windows on the rig timebase.
2. **keyframes**: the counts of all sensors together give one segmentation of the sequence
   (paper Sec. 3.3, `reconstruction.partition.segment_starts`). The keyframe candidates are the
   RGB frames' mid-exposure times (a regular grid for takes without cameras), at most
   `max_candidates` per segment. The blocks are filtered again and summed into signed event maps
   between candidates; per segment the canonical keyframe (Eq. 3) is chosen over the maps of all
   sensors side by side.
3. **snapshots**: a log-intensity image of every sensor at every keyframe (high-pass integration
   over the time constants before it, or direct integration from the segment start).

Output per take: `<out>/<take_id>/segments.json` (the segments, keyframes, candidate source,
what the filter kept per sensor, the options), `<out>/<take_id>/<sensor>/snapshots.npz`, and
`<out>/<take_id>/overview.png` (the event rate with the segments and keyframes on it, and keyframe
snapshots per sensor: `reconstruct_picture`).

Scheduling: the same Dask graph runs on local threads (default), local processes, the
synchronous scheduler, or a `dask.distributed` cluster (`reconstruct_scheduler`); the options and
results are in `reconstruct_options`. A take
that cannot be read fails alone: its result carries `error` (one line naming the take).
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import time
import zipfile
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from reconstruction.partition import Segment, canonical_keyframe, map_shape, segment_starts
from rigd.core.errors import ConfigError, RigdError
from rigd.core.layout import FRAMES_GROUP, Frames
from rigd.core.progress import ProgressCallback, ProgressUpdate, no_progress
from rigd.products.reconstruct_options import ReconstructOptions, SensorReconstruction, TakeReconstruction
from rigd.products.reconstruct_picture import picks, write_overview
from rigd.products.reconstruct_scheduler import DaskRunner
from rigd.products.reconstruct_tasks import (
    BlockMaps,
    BlockScan,
    Grid,
    Snapshot,
    highpass_warmup_us,
    map_block,
    scan_block,
    snapshot,
)
from rigd.take.linked import open_take_h5
from rigd.take.reader import Take

log = logging.getLogger(__name__)

#: The progress stages, each counted in its own unit (events, events, snapshots).
STAGE_FILTER, STAGE_MAPS, STAGE_SNAPSHOTS = "filter + activity", "keyframe maps", "snapshots"


@dataclass(frozen=True, slots=True)
class _Plan:
    """What a take holds that the graph is built from (read once, on the caller's side)."""

    path: Path
    take_id: str
    geometry: dict[str, tuple[int, int]]
    blocks: dict[str, list[tuple[int, int]]]
    t0_us: int
    t1_us: int
    candidates: NDArray[np.int64]
    candidate_source: str

    @property
    def n_events(self) -> int:
        return sum(hi - lo for b in self.blocks.values() for lo, hi in b)


# --- planning -----------------------------------------------------------------------------------


def _mid_exposures(path: Path, camera: str) -> NDArray[np.int64]:
    """Mid-exposure rig times of a camera's frames (exposure start + half the exposure)."""
    with open_take_h5(path) as f:  # a joined take's camera lives in its host's part
        g = f[f"{FRAMES_GROUP}/{camera}"]
        n = int(g[Frames.IMAGES].shape[0])
        start = np.asarray(g[Frames.T_EXPOSURE_START][:n], np.int64)
        exposure = np.asarray(g[Frames.EXPOSURE][:n], np.int64)
    return start + exposure // 2


def _plan(path: Path, o: ReconstructOptions) -> _Plan:
    with Take(path) as take:
        sensors = take.event_sensors
        geometry = {s: take.sensor(s).geometry for s in sensors}
        blocks: dict[str, list[tuple[int, int]]] = {}
        spans = []
        for s in sensors:
            n = take.sensor(s).count
            blocks[s] = [(lo, min(lo + o.block_events, n)) for lo in range(0, n, o.block_events)]
            span = take.sensor(s).span if n else None
            if span is not None:
                spans.append(span)
        cameras = [c for c in take.cameras if len(take.camera(c))]
        take_id = take.take_id or path.stem
    t0 = min((a for a, _ in spans), default=0)
    t1 = max((b for _, b in spans), default=0) + 1
    if o.keyframe_camera is not None and o.keyframe_camera not in cameras:
        raise ConfigError(
            f"{path}: --keyframe-camera {o.keyframe_camera!r} is not a camera with frames here "
            f"(it has {', '.join(cameras) or 'none'})"
        )
    camera = o.keyframe_camera or (cameras[0] if cameras else None)
    if camera is not None:
        cand = _mid_exposures(path, camera)
        source = f"{camera} mid-exposure"
    else:
        cand = np.arange(t0, t1, o.candidate_interval_us, dtype=np.int64)
        source = f"every {o.candidate_interval_us} us (no camera frames)"
    cand = np.unique(cand[(cand >= t0) & (cand < t1)])
    return _Plan(path, take_id, geometry, blocks, t0, t1, cand, source)


def _even_subset(values: NDArray[np.int64], n_max: int) -> NDArray[np.int64]:
    """At most n_max of the sorted values, evenly spaced, first and last kept (0: all)."""
    if n_max <= 0 or len(values) <= n_max:
        return values
    return values[np.unique(np.linspace(0, len(values) - 1, n_max).round().astype(np.int64))]


# --- the phases -----------------------------------------------------------------------------------


def _keyframe(
    a: int,
    b: int,
    cand_cuts: NDArray[np.int64],
    cuts: NDArray[np.int64],
    shapes: dict[str, tuple[int, int]],
    *block_maps: BlockMaps,
) -> int:
    """Canonical keyframe time of the segment [cuts[a], cuts[b]) among the cut indices `cand_cuts`.

    E(tau) of each sensor is the prefix sum of its interval maps from the segment start; the
    sensors' maps are laid side by side, so Eq. 3's L1 distance runs over every pixel of the rig.
    """
    if len(cand_cuts) == 0:
        return int(cuts[a])
    n_pix = sum(sh * sw for sh, sw in shapes.values())
    maps = np.empty((len(cand_cuts), n_pix), np.int32)
    col = 0
    for sensor, (sh, sw) in shapes.items():
        # acc[j] = E(cuts[a + j]): a zero row, then the running sum of the intervals a, a+1, ...
        acc = np.zeros((b - a + 1, sh, sw), np.int32)
        for bm in block_maps:
            if bm.sensor != sensor:
                continue
            lo, hi = max(a, bm.i0), min(b, bm.i0 + len(bm.maps))
            if lo < hi:
                acc[lo - a + 1 : hi - a + 1] += bm.maps[lo - bm.i0 : hi - bm.i0]
        np.cumsum(acc, axis=0, out=acc)
        maps[:, col : col + sh * sw] = acc[cand_cuts - a].reshape(len(cand_cuts), -1)
        col += sh * sw
        del acc
    return int(cuts[cand_cuts[canonical_keyframe(maps, overwrite=True)]])


def reconstruct_take(
    path: Path,
    options: ReconstructOptions,
    progress: ProgressCallback = no_progress,
    runner: DaskRunner | None = None,
) -> TakeReconstruction:
    """The three phases on one take; writes its outputs. Raises RigdError / OSError on a bad take."""
    o = options
    own = runner is None
    run = runner or DaskRunner(o.scheduler, o.workers)
    started = time.perf_counter()
    try:
        plan = _plan(path, o)
        result = _phases(plan, o, run, progress)
    finally:
        if own:
            run.close()
    return result.model_copy(update={"seconds": round(time.perf_counter() - started, 3)})


def _phases(
    plan: _Plan, o: ReconstructOptions, run: DaskRunner, progress: ProgressCallback
) -> TakeReconstruction:
    name = str(plan.path)
    sensors = list(plan.blocks)
    if not sensors or plan.n_events == 0:
        empty = {s: SensorReconstruction(events_in=0, events_kept=0) for s in sensors}
        _write(plan, o, [], empty)
        return TakeReconstruction(take=name, sensors=empty)
    act = _scan(plan, o, run, progress)
    chosen, keys = _keyframes(plan, o, run, progress, act)
    shots = _snapshots(plan, o, run, progress, keys, act.edges)
    cfg = o.partition_config()
    segments = []
    for g, k in enumerate(keys):
        lo, hi = act.starts[g], (act.starts[g + 1] if g + 1 < len(act.starts) else act.grid.n)
        ne = int(act.counts[lo:hi].sum())
        segments.append(Segment(g, int(act.edges[g]), int(act.edges[g + 1]), k, ne, ne / act.n_pix))
    per_sensor = {
        s: SensorReconstruction(events_in=sum(h - lo for lo, h in plan.blocks[s]), events_kept=act.kept[s])
        for s in sensors
    }
    _write(plan, o, segments, per_sensor, n_candidates=sum(len(c) for c in chosen))
    write_overview(
        o.out / plan.take_id / "overview.png",
        act.counts,
        cfg.window_us,
        plan.t0_us,
        segments,
        shots,
        plan.geometry,
    )
    log.info(
        "%s: %d segments; %s",
        plan.take_id,
        len(segments),
        ", ".join(f"{s} kept {v.events_kept} of {v.events_in}" for s, v in per_sensor.items()),
    )
    return TakeReconstruction(take=name, segments=len(segments), sensors=per_sensor)


def _counting_events(
    progress: ProgressCallback, stage: str, name: str, n_total: int
) -> Callable[[Any], None]:
    """An `on_result` that reports the events of the finished scans and maps of one stage."""
    done = [0]

    def on_result(r: Any) -> None:
        if isinstance(r, BlockScan | BlockMaps):
            done[0] += r.n_events
            progress(ProgressUpdate(stage, name, done[0], n_total, "events"))

    return on_result


@dataclass(slots=True)
class _Activity:
    """Phase 1's outcome: what every block kept, counted per window of the rig, and the one
    segmentation of the take those counts give."""

    scans: list[BlockScan]
    grid: Grid
    counts: NDArray[np.int64]
    kept: dict[str, int]
    n_pix: int
    """Pixels of all sensors together (the segmentation's budget is per pixel of the rig)."""
    starts: list[int]
    """Window index where each segment starts."""
    edges: NDArray[np.int64]
    """Rig times the segments start at, then the take's end."""


def _scan(plan: _Plan, o: ReconstructOptions, run: DaskRunner, progress: ProgressCallback) -> _Activity:
    """Phase 1: filter every block, count what it kept per window, and segment the take."""
    from dask import delayed  # dask is checked by DaskRunner, with its own message

    cfg, name, total = o.partition_config(), str(plan.path), plan.n_events
    grid = Grid(plan.t0_us, cfg.window_us, max(1, -(-(plan.t1_us - plan.t0_us) // cfg.window_us)))
    progress(ProgressUpdate(STAGE_FILTER, name, 0, total, "events"))
    scan_tasks = [
        delayed(scan_block)(plan.path, s, lo, hi, grid, o.filter)
        for s, blocks in plan.blocks.items()
        for lo, hi in blocks
    ]
    scans: list[BlockScan] = run.compute(scan_tasks, _counting_events(progress, STAGE_FILTER, name, total))
    counts = np.zeros(grid.n, np.int64)
    kept = {s: 0 for s in plan.blocks}
    for sc in scans:
        counts[sc.k0 : sc.k0 + len(sc.counts)] += sc.counts
        kept[sc.sensor] += sc.n_kept
    n_pix = sum(w * h for w, h in plan.geometry.values())
    starts = segment_starts(counts, n_pix, cfg)
    seg_t = np.array([plan.t0_us + s * cfg.window_us for s in starts], np.int64)
    return _Activity(scans, grid, counts, kept, n_pix, starts, np.append(seg_t, plan.t1_us))


def _keyframes(
    plan: _Plan, o: ReconstructOptions, run: DaskRunner, progress: ProgressCallback, act: _Activity
) -> tuple[list[NDArray[np.int64]], list[int]]:
    """Phase 2: interval maps between the chosen candidates, canonical keyframe per segment.
    Returns the candidates chosen per segment and the keyframes."""
    from dask import delayed

    cfg, name, edges = o.partition_config(), str(plan.path), act.edges
    chosen = [
        _even_subset(plan.candidates[(plan.candidates >= a) & (plan.candidates < b)], o.max_candidates)
        for a, b in itertools.pairwise(edges)
    ]
    cuts = np.unique(np.concatenate([edges, *chosen]))
    shapes = {s: map_shape(*plan.geometry[s], cfg.map_scale) for s in plan.blocks}
    map_tasks: list[tuple[str, int, int, Any]] = []
    for sc in act.scans:
        if sc.n_kept == 0:
            continue
        i_a = max(0, int(np.searchsorted(cuts, sc.t_first_us, side="right")) - 1)
        i_b = min(len(cuts) - 2, int(np.searchsorted(cuts, sc.t_last_us, side="right")) - 1)
        task = delayed(map_block)(
            plan.path, sc.sensor, sc.lo, sc.hi, cuts[i_a : i_b + 2], i_a, o.filter, cfg.map_scale
        )
        map_tasks.append((sc.sensor, i_a, i_b, task))
    key_tasks = []
    for g, (a_t, b_t) in enumerate(itertools.pairwise(edges)):
        a, b = int(np.searchsorted(cuts, a_t)), int(np.searchsorted(cuts, b_t))
        cand_cuts = np.searchsorted(cuts, chosen[g]).astype(np.int64)
        deps = [t for _, i_a, i_b, t in map_tasks if i_a < b and i_b >= a]
        key_tasks.append(delayed(_keyframe)(a, b, cand_cuts, cuts, shapes, *deps))
    n_mapped = sum(sc.n_events for sc in act.scans if sc.n_kept)
    progress(ProgressUpdate(STAGE_MAPS, name, 0, n_mapped, "events"))
    keys = [int(k) for k in run.compute(key_tasks, _counting_events(progress, STAGE_MAPS, name, n_mapped))]
    return chosen, keys


def _snapshots(
    plan: _Plan,
    o: ReconstructOptions,
    run: DaskRunner,
    progress: ProgressCallback,
    keys: list[int],
    edges: NDArray[np.int64],
) -> dict[str, list[tuple[int, NDArray[np.float32]]]]:
    """Phase 3: one snapshot per sensor and keyframe, streamed to disk in batches (memory does
    not grow with the number of keyframes). Returns the few the overview shows."""
    from dask import delayed

    name, path = str(plan.path), plan.path
    warm = highpass_warmup_us(o.cutoff_hz)
    n_snaps = len(plan.blocks) * len(keys)
    snapped = [0]

    def on_snapshot(r: Any) -> None:
        if isinstance(r, Snapshot):
            snapped[0] += 1
            progress(ProgressUpdate(STAGE_SNAPSHOTS, name, snapped[0], n_snaps, "snapshots"))

    progress(ProgressUpdate(STAGE_SNAPSHOTS, name, 0, n_snaps, "snapshots"))
    batch = max(8, 4 * (o.workers or os.cpu_count() or 1))
    shown = set(picks(len(keys)))
    shots: dict[str, list[tuple[int, NDArray[np.float32]]]] = {s: [] for s in plan.blocks}
    for s in plan.blocks:
        w, h = plan.geometry[s]
        with _SnapshotFile(o.out / plan.take_id / s / "snapshots.npz", len(keys), h, w) as dest:
            for i in range(0, len(keys), batch):
                tasks = [
                    delayed(snapshot)(
                        path,
                        s,
                        (k - warm) if o.e2i == "highpass" else int(edges[g]),
                        k,
                        o.filter,
                        o.e2i,
                        o.contrast,
                        o.cutoff_hz,
                        o.block_events,
                    )
                    for g, k in enumerate(keys[i : i + batch], start=i)
                ]
                for j, snap in enumerate(run.compute(tasks, on_snapshot), start=i):
                    dest.append(snap.t_us, snap.image)
                    if j in shown:  # the few the overview shows; the rest only go to disk
                        shots[s].append((snap.t_us, snap.image))
    return shots


def _write(
    plan: _Plan,
    o: ReconstructOptions,
    segments: list[Segment],
    sensors: dict[str, SensorReconstruction],
    n_candidates: int = 0,
) -> None:
    base = o.out / plan.take_id
    base.mkdir(parents=True, exist_ok=True)
    doc = {
        "take": str(plan.path),
        "take_id": plan.take_id,
        "t_start_us": plan.t0_us,
        "t_end_us": plan.t1_us,
        "candidates": {
            "source": plan.candidate_source,
            "available": len(plan.candidates),
            "used": n_candidates,
        },
        "sensors": {s: v.model_dump() | {"geometry": list(plan.geometry[s])} for s, v in sensors.items()},
        "options": o.model_dump(mode="json", exclude={"takes", "out", "scheduler", "workers"}),
        "segments": [asdict(s) for s in segments],
    }
    (base / "segments.json").write_text(json.dumps(doc, indent=2))


class _SnapshotFile:
    """`snapshots.npz` (`times_us`, `log_intensity` (n, H, W) float32) written one image at a time.

    The npz is a zip of .npy members; the image member's header is written first (n is known), then
    each image's bytes as it comes, so only one snapshot is ever held. It is written to a temporary
    name and renamed when complete: a failed run leaves no half file under the real name.
    """

    def __init__(self, path: Path, n: int, height: int, width: int) -> None:
        self.path = path
        self._n, self._shape = n, (height, width)
        self._times: list[int] = []
        path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = path.with_name(path.name + ".partial")
        self._zip = zipfile.ZipFile(self._tmp, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1)
        self._member = self._zip.open("log_intensity.npy", "w", force_zip64=True)
        header = {"descr": np.lib.format.dtype_to_descr(np.dtype(np.float32)), "fortran_order": False}
        np.lib.format.write_array_header_2_0(self._member, header | {"shape": (n, height, width)})

    def append(self, t_us: int, image: NDArray[np.float32]) -> None:
        if image.shape != self._shape or len(self._times) >= self._n:
            raise RigdError(f"{self.path}: snapshot {len(self._times)} of shape {image.shape} does not fit")
        self._member.write(np.ascontiguousarray(image, np.float32).tobytes())
        self._times.append(int(t_us))

    def __enter__(self) -> _SnapshotFile:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self._member.close()
        if exc_type is None and len(self._times) != self._n:
            self._zip.close()
            self._tmp.unlink(missing_ok=True)
            raise RigdError(f"{self.path}: {len(self._times)} of {self._n} snapshots written")
        if exc_type is None:
            with self._zip.open("times_us.npy", "w") as f:
                np.lib.format.write_array(f, np.asarray(self._times, np.int64))
        self._zip.close()
        if exc_type is None:
            self._tmp.replace(self.path)
        else:
            self._tmp.unlink(missing_ok=True)


def _failed(path: Path, exc: Exception) -> TakeReconstruction:
    """The failed take's result: one line naming the take (prefixed when the error does not)."""
    msg = " ".join(str(exc).split()) or type(exc).__name__
    if str(path) not in msg:
        msg = f"{path}: {msg}"
    log.debug("reconstruct of %s failed", path, exc_info=exc)
    return TakeReconstruction(take=str(path), error=msg)


def run_reconstruct(
    options: ReconstructOptions, progress: ProgressCallback = no_progress
) -> list[TakeReconstruction]:
    """Every take in turn, each spread over the scheduler's workers; results in input order.

    A take failing with a RigdError or OSError (h5py's read errors) gets `error` set; the others run.
    """
    o = options
    runner = DaskRunner(o.scheduler, o.workers)  # first: an unreachable scheduler leaves nothing behind
    try:
        o.out.mkdir(parents=True, exist_ok=True)
    except BaseException:
        runner.close()
        raise
    results = []
    try:
        for path in o.takes:
            try:
                results.append(reconstruct_take(path, o, progress, runner))
            except (RigdError, OSError) as exc:
                results.append(_failed(path, exc))
    finally:
        runner.close()
    return results
