"""`rigd reconstruct TAKE... --out DIR [--scheduler ADDR]`: denoise, partition and snapshots per take.

This module joins the reconstruction library with takes (the layering rule keeps `reconstruction`
free of rigd.take). Each take is one Dask task: takes are independent, so batch processing scales
over a local process pool by default, or over a distributed cluster when `--scheduler` gives its
address (`tcp://host:8786`). Per take and event sensor the output directory gets
`<take_id>/<sensor>/segments.json` (segment boundaries and canonical keyframes) and
`snapshots.npz` (high-pass log-intensity snapshots at the keyframes, denoised event count).
Register with `app.command("reconstruct")(reconstruct)`.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer
from rich.console import Console
from rich.progress import Progress

from reconstruction.e2i import reconstruct as e2i_reconstruct
from reconstruction.filters import BackgroundActivityFilter
from reconstruction.partition import PartitionConfig, export_segments, partition
from rigd.core.events import EventArray
from rigd.take.reader import Take

log = logging.getLogger(__name__)

_err = Console(stderr=True)
CHUNK_US = 100_000


def process_take(path: str, out_dir: str, contrast: float = 0.3, cutoff_hz: float = 5.0) -> dict[str, Any]:
    """Denoise + partition + keyframe snapshots of every event sensor of one take (one Dask task)."""
    result: dict[str, Any] = {"take": path, "sensors": {}}
    with Take(path) as take:
        base = Path(out_dir) / take.take_id
        for sensor in take.event_sensors:
            w, h = take.geometry(sensor)
            baf = BackgroundActivityFilter(w, h)
            kept = [baf.filter(chunk) for chunk in take.iter_events(sensor, CHUNK_US)]
            ev = EventArray.concatenate(kept)
            dest = base / sensor
            dest.mkdir(parents=True, exist_ok=True)
            if len(ev) == 0:
                export_segments([], dest / "segments.json")
                result["sensors"][sensor] = {"events_in": baf.n_in, "events_kept": 0, "segments": 0}
                continue
            segs = partition(ev, w, h, config=PartitionConfig())
            export_segments(segs, dest / "segments.json")
            keys = np.array([s.keyframe_us for s in segs], np.int64)
            snaps = e2i_reconstruct(ev, w, h, keys, "highpass", contrast=contrast, cutoff_hz=cutoff_hz)
            np.savez_compressed(dest / "snapshots.npz", times_us=keys, log_intensity=snaps)
            result["sensors"][sensor] = {
                "events_in": baf.n_in,
                "events_kept": baf.n_kept,
                "segments": len(segs),
            }
            log.info(
                "%s/%s: %d of %d events kept, %d segments",
                take.take_id,
                sensor,
                baf.n_kept,
                baf.n_in,
                len(segs),
            )
    return result


def run_batch(takes: list[str], out: str, scheduler: str | None = None) -> list[dict[str, Any]]:
    """All takes through Dask with a rich progress bar; results in input order."""
    try:
        import dask
        from dask import delayed
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise RuntimeError(
            "rigd reconstruct needs dask: pip install dask (distributed for --scheduler)"
        ) from exc
    tasks = [delayed(process_take)(t, out) for t in takes]
    results: list[dict[str, Any]] = [{} for _ in takes]
    with Progress(console=_err, transient=False) as progress:
        bar = progress.add_task("reconstruct", total=len(takes))
        if scheduler:
            from dask.distributed import Client, as_completed

            with Client(scheduler) as client:
                futures = client.compute(tasks)
                index = {f.key: i for i, f in enumerate(futures)}
                for fut in as_completed(futures):
                    results[index[fut.key]] = fut.result()
                    progress.advance(bar)
        else:
            # Local scheduler: threads (the kernels release the GIL); one task per take.
            for i, task in enumerate(tasks):
                (results[i],) = dask.compute(task, scheduler="threads")
                progress.advance(bar)
    return results


def reconstruct(
    takes: Annotated[list[Path], typer.Argument(help="Take files (.h5).", exists=True, dir_okay=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output directory.")],
    scheduler: Annotated[
        str | None, typer.Option("--scheduler", help="Dask distributed scheduler address; local if omitted.")
    ] = None,
) -> None:
    """Denoise, partition into motion-aware segments and reconstruct keyframe snapshots per take."""
    out.mkdir(parents=True, exist_ok=True)
    results = run_batch([str(t) for t in takes], str(out), scheduler)
    for r in results:
        for sensor, s in r["sensors"].items():
            kept = f"{s['events_kept']}/{s['events_in']}"
            _err.print(f"{r['take']} {sensor}: {kept} events kept, {s['segments']} segments")
