"""Batch reconstruction of takes: denoise, partition into segments, keyframe snapshots.

This joins the reconstruction library with takes (the layering rule keeps `reconstruction` free of
rigd.take). Each take is one Dask task: takes are independent, so a batch scales over a local
thread pool by default, or over a distributed cluster when `scheduler` gives its address
(`tcp://host:8786`). Per take and event sensor the output directory gets
`<take_id>/<sensor>/segments.json` (segment boundaries and canonical keyframes) and
`snapshots.npz` (high-pass log-intensity snapshots at the keyframes).
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
from rigd.core.errors import RigdError
from rigd.core.events import EventArray
from rigd.take.reader import Take

log = logging.getLogger(__name__)

#: Events are denoised in chunks of this span (us), so a long take never sits in memory twice.
CHUNK_US = 100_000


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
    """One take's outcome; `take` is the path as given."""

    take: str
    sensors: dict[str, SensorReconstruction] = {}


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


def _reconstruct_sensor(
    take: Take, sensor: str, dest: Path, contrast: float, cutoff_hz: float
) -> SensorReconstruction:
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


def run_reconstruct(
    options: ReconstructOptions, progress: ProgressCallback = no_progress
) -> list[TakeReconstruction]:
    """All takes through Dask; results in input order, progress once per finished take."""
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
                results[index[fut.key]] = fut.result()
                progress(ProgressUpdate("reconstruct", str(o.takes[index[fut.key]]), done, n))
    else:
        # Local scheduler: threads (the kernels release the GIL); one task per take.
        for i, task in enumerate(tasks):
            (results[i],) = dask.compute(task, scheduler="threads")
            progress(ProgressUpdate("reconstruct", str(o.takes[i]), i + 1, n))
    return [results[i] for i in range(n)]
