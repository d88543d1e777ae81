"""`rigd export`: a calibrated take as the input of a 4D reconstruction trainer or event loader.

One `ExportPlan` (rigd.app.export.common) is built from the take and written by one module per
format; the event-sensor products (maps, voxel grids, segments) are common to every format.
See docs/export.md for the layouts and conventions.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

from pydantic import BaseModel, ConfigDict

from rigd.app.export import colmap, dsec, dynamic3dgs, nerfstudio
from rigd.app.export.common import FORMATS, ExportOptions, ExportPlan, cameras_of, frame_table, parse_size
from rigd.app.export.sensors import write_event_products
from rigd.app.workflows.progress import ProgressCallback, ProgressUpdate, no_progress
from rigd.core.errors import ConfigError, TakeError
from rigd.take.reader import open_take

__all__ = ["FORMATS", "ExportOptions", "ExportResult", "parse_size", "run_export"]

log = logging.getLogger(__name__)


class ExportResult(BaseModel):
    """What was written, for the CLI's one-line summary and for export.json."""

    model_config = ConfigDict(extra="forbid")

    take: str
    take_id: str
    format: str
    out: str
    timesteps: int
    cameras: list[str]
    train: int
    test: int
    event_sensors: list[str]
    t0_us: int
    t1_us: int
    wall_s: float
    bytes: int


def _check_out(out: Path) -> None:
    if not out.parent.is_dir():
        raise ConfigError(f"--out {out}: parent directory {out.parent} does not exist")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ConfigError(f"--out {out}: exists and is not an empty directory")


def _disk_bytes(root: Path) -> int:
    """Bytes under root, each file once (the colmap tree hard-links its frames)."""
    seen: dict[tuple[int, int], int] = {}
    for p in root.rglob("*"):
        if p.is_file():
            st = p.stat()
            seen[(st.st_dev, st.st_ino)] = st.st_size
    return sum(seen.values())


def run_export(options: ExportOptions, progress: ProgressCallback = no_progress) -> ExportResult:
    """Write the take in the chosen format under options.out (created)."""
    if not options.take.is_file():
        raise TakeError(f"no such take: {options.take}")
    _check_out(options.out)
    start = time.perf_counter()
    with open_take(options.take) as take:
        if take.time_domain != "rig":
            raise TakeError(f"{take.path}: not on the rig timebase (time domain {take.time_domain})")
        if not take.cameras:
            raise TakeError(f"{take.path}: no RGB camera to export")
        cameras = cameras_of(take, options.resize)
        frames = frame_table(take, take.cameras)
        options.out.mkdir(exist_ok=True)
        plan = ExportPlan(options=options, take=take, cameras=cameras, frames=frames, progress=progress)
        progress(ProgressUpdate("images", f"0/{plan.images()} frames", 0, plan.images()))
        writer = {
            "dynamic3dgs": dynamic3dgs.write,
            "nerfstudio": nerfstudio.write,
            "colmap": colmap.write,
            "dsec": dsec.write,
        }[options.format]
        writer(plan)
        write_event_products(plan)
        result = ExportResult(
            take=str(take.path),
            take_id=take.take_id,
            format=options.format,
            out=str(options.out),
            timesteps=int(frames.pulses.size),
            cameras=[c.name for c in cameras],
            train=int(frames.train.sum()),
            test=int((~frames.train).sum()),
            event_sensors=take.event_sensors,
            t0_us=frames.t0_us,
            t1_us=frames.t1_us,
            wall_s=0.0,
            bytes=0,
        )
    result.wall_s = round(time.perf_counter() - start, 3)
    result.bytes = _disk_bytes(options.out)
    (options.out / "export.json").write_text(json.dumps(result.model_dump(), indent=2))
    log.info("exported %s as %s to %s in %.1f s", options.take, options.format, options.out, result.wall_s)
    return result
