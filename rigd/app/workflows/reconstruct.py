"""Batch reconstruction of takes: denoise, partition into segments, keyframe snapshots.

This joins the reconstruction library with takes (the layering rule keeps `reconstruction` free of
rigd.take). Each take is one Dask task: takes are independent, so a batch scales over a local
thread pool by default, or over a distributed cluster when `scheduler` gives its address
(`tcp://host:8786`). Per take and event sensor the output directory gets
`<take_id>/<sensor>/segments.json` (segment boundaries and canonical keyframes) and
`snapshots.npz` (high-pass log-intensity snapshots at the keyframes).

A take that cannot be read (not HDF5, truncated, a dataset missing, event times going back)
fails alone: its result carries `error` (one line naming the take) and the others still run.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict

from reconstruction.e2i import reconstruct as e2i_reconstruct
from reconstruction.filters import BackgroundActivityFilter
from reconstruction.partition import PartitionConfig, export_segments, partition
from rigd.app.workflows.progress import ProgressCallback, ProgressUpdate, no_progress
from rigd.core.errors import RigdError, TakeFormatError
from rigd.core.events import EventArray
from rigd.take.reader import Take

log = logging.getLogger(__name__)

#: Events are denoised in chunks of this span (us), so a long take never sits in memory twice.
CHUNK_US = 100_000
#: Events read per step by the time-order check.
_CHECK_BLOCK = 1_000_000


class ReconstructOptions(BaseModel):
    """Takes to reconstruct, where to, and on which Dask scheduler (None: local threads)."""

    model_config = ConfigDict(frozen=True)

    takes: list[Path]
    out: Path
    scheduler: str | None = None
    contrast: float = 0.3
    cutoff_hz: float = 5.0


class SensorReconstruction(BaseModel):
    """What denoising kept of one sensor's events, and how many segments they fell into."""

    events_in: int
    events_kept: int
    segments: int


class TakeReconstruction(BaseModel):
    """One take's outcome; `take` is the path as given, `error` one line when it failed."""

    take: str
    sensors: dict[str, SensorReconstruction] = {}
    error: str | None = None


def reconstruct_take(
    path: Path, out_dir: Path, contrast: float = 0.3, cutoff_hz: float = 5.0
) -> TakeReconstruction:
    """Denoise + partition + keyframe snapshots of every event sensor of one take (one Dask task)."""
    result = TakeReconstruction(take=str(path))
    with Take(path) as take:
        base = out_dir / take.take_id
        for sensor in take.event_sensors:
            result.sensors[sensor] = _reconstruct_sensor(take, sensor, base / sensor, contrast, cutoff_hz)
    return result


def _check_time_order(take: Take, sensor: str) -> None:
    """TakeFormatError naming the take and index where a sensor's event times go backwards."""
    n = take.event_count(sensor)
    last: int | None = None
    for lo in range(0, n, _CHECK_BLOCK):
        t = take.events_by_index(sensor, lo, lo + _CHECK_BLOCK).t
        if len(t) == 0:
            break
        if last is not None and int(t[0]) < last:
            bad = lo
        else:
            back = np.flatnonzero(np.diff(t) < 0)
            bad = lo + int(back[0]) + 1 if len(back) else -1
        if bad >= 0:
            raise TakeFormatError(
                f"{take.path}: /events/{sensor}/t: event times go backwards at index {bad} (damaged take)"
            )
        last = int(t[-1])


def _reconstruct_sensor(
    take: Take, sensor: str, dest: Path, contrast: float, cutoff_hz: float
) -> SensorReconstruction:
    _check_time_order(take, sensor)
    w, h = take.geometry(sensor)
    baf = BackgroundActivityFilter(w, h)
    ev = EventArray.concatenate([baf.filter(chunk) for chunk in take.iter_events(sensor, CHUNK_US)])
    dest.mkdir(parents=True, exist_ok=True)
    if len(ev) == 0:
        export_segments([], dest / "segments.json")
        return SensorReconstruction(events_in=baf.n_in, events_kept=0, segments=0)
    segs = partition(ev, w, h, config=PartitionConfig())
    export_segments(segs, dest / "segments.json")
    keys = np.array([s.keyframe_us for s in segs], np.int64)
    snaps = e2i_reconstruct(ev, w, h, keys, "highpass", contrast=contrast, cutoff_hz=cutoff_hz)
    np.savez_compressed(dest / "snapshots.npz", times_us=keys, log_intensity=snaps)
    log.info(
        "%s/%s: %d of %d events kept, %d segments", take.take_id, sensor, baf.n_kept, baf.n_in, len(segs)
    )
    return SensorReconstruction(events_in=baf.n_in, events_kept=baf.n_kept, segments=len(segs))


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
    """All takes through Dask; results in input order, progress once per finished take.

    A take failing with a RigdError or OSError (h5py's read errors) gets `error` set; others run.
    """
    try:
        import dask
        from dask import delayed
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise RigdError(
            "rigd reconstruct needs dask: pip install dask (distributed for --scheduler)"
        ) from exc
    o = options
    o.out.mkdir(parents=True, exist_ok=True)
    tasks = [delayed(reconstruct_take)(t, o.out, o.contrast, o.cutoff_hz) for t in o.takes]
    results: dict[int, TakeReconstruction] = {}
    n = len(tasks)
    if o.scheduler:
        from dask.distributed import Client, as_completed

        with Client(o.scheduler) as client:
            futures = client.compute(tasks)
            index = {f.key: i for i, f in enumerate(futures)}
            for done, fut in enumerate(as_completed(futures), 1):
                i = index[fut.key]
                try:
                    results[i] = fut.result()
                except (RigdError, OSError) as exc:
                    results[i] = _failed(o.takes[i], exc)
                progress(ProgressUpdate("reconstruct", str(o.takes[i]), done, n))
    else:
        # Local scheduler: threads (the kernels release the GIL); one task per take.
        for i, task in enumerate(tasks):
            try:
                (results[i],) = dask.compute(task, scheduler="threads")
            except (RigdError, OSError) as exc:
                results[i] = _failed(o.takes[i], exc)
            progress(ProgressUpdate("reconstruct", str(o.takes[i]), i + 1, n))
    return [results[i] for i in range(n)]
