"""`rigd export`: a calibrated take as the input of a 4D reconstruction trainer or event loader.

One `ExportPlan` (rigd.products.export.common) is built from the take and written by one module per
format; the event-sensor products (maps, voxel grids, segments) are common to every format.
See docs/export.md for the layouts and conventions.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict

from rigd.core.errors import TakeError
from rigd.core.progress import ProgressCallback, ProgressUpdate, no_progress
from rigd.products.export import bounds, colmap, dsec, dynamic3dgs, nerfstudio
from rigd.products.export.common import (
    FORMATS,
    IMAGE_THREADS,
    SPLITS,
    UNCALIBRATED_FORMATS,
    WORLDS,
    Camera,
    ExportOptions,
    ExportPlan,
    FrameTable,
    cameras_of,
    frame_table,
    parse_count,
    parse_size,
    test_camera_positions,
)
from rigd.products.export.sensors import voxel_windows, write_event_products
from rigd.products.export.staging import ExportWriteError, Staging, check_target
from rigd.products.export.world import apply_world
from rigd.take.reader import Take, open_take

__all__ = [
    "FORMATS",
    "SPLITS",
    "WORLDS",
    "ExportOptions",
    "ExportResult",
    "ExportWriteError",
    "parse_count",
    "parse_size",
    "run_export",
]

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
    """Views (timestep, camera) that train."""
    test: int
    split: str
    test_cameras: list[str]
    world: str
    rig_to_world: list[list[float]]
    """4x4: x_world = rig_to_world @ x_rig (the rig frame of the take's calibration)."""
    event_sensors: list[str]
    t0_us: int
    t1_us: int
    wall_s: float
    bytes: int


def _disk_bytes(root: Path) -> int:
    """Bytes under root, each file once (the colmap tree hard-links its frames)."""
    seen: dict[tuple[int, int], int] = {}
    for p in root.rglob("*"):
        if p.is_file():
            st = p.stat()
            seen[(st.st_dev, st.st_ino)] = st.st_size
    return sum(seen.values())


def check_sizes(options: ExportOptions, take: Take, frames: FrameTable) -> None:
    """Every size knob against the format's and the machine's bounds (rigd.products.export.bounds)."""
    budget = bounds.Budget(bounds.available_memory())
    if options.resize is not None:
        bounds.check_resize(options.resize, options.format, IMAGE_THREADS, budget)
    geometry = {s: take.sensor(s).geometry for s in take.event_sensors}
    bounds.check_voxel_bins(options.voxel_bins, geometry, voxel_windows(frames.step_times_us), budget)


@contextmanager
def _committed(options: ExportOptions, staging: Staging) -> Iterator[None]:
    """The staged output is committed when the body finishes; a failure removes it and raises
    the clearer error `_write_failed` makes of it."""
    try:
        yield
        staging.commit()
    except BaseException as exc:
        replaced = _write_failed(options, staging, exc)
        if replaced is not None:
            raise replaced from exc
        raise


def _write_failed(options: ExportOptions, staging: Staging, exc: BaseException) -> ExportWriteError | None:
    """Remove the partial output after a failure; the error to raise instead of exc (None: exc)."""
    try:
        staging.discard()
    except OSError as rm:
        return ExportWriteError(
            f"--out {options.out}: the export failed ({exc}) and its partial output in {staging.dir} "
            f"could not be removed ({rm}); remove it by hand"
        )
    kept = "unchanged" if options.out.exists() else "not created"
    if isinstance(exc, OSError):
        what = " ".join((exc.strerror or str(exc)).split())
        where = ""
        if exc.filename:
            name = Path(exc.filename)
            where = f" ({name.relative_to(staging.dir) if name.is_relative_to(staging.dir) else name})"
        return ExportWriteError(
            f"--out {options.out}: writing the {options.format} export failed: {what}{where}; "
            f"the partial output was removed, {options.out} is {kept}"
        )
    if isinstance(exc, MemoryError):
        return ExportWriteError(
            f"--out {options.out}: out of memory while writing the {options.format} export; "
            f"the partial output was removed, {options.out} is {kept}"
        )
    return None


def run_export(options: ExportOptions, progress: ProgressCallback = no_progress) -> ExportResult:
    """Write the take in the chosen format to options.out: staged beside it, renamed when complete."""
    if not options.take.is_file():
        raise TakeError(f"no such take: {options.take}")
    leftovers = check_target(options.out, options.force)
    start = time.perf_counter()
    if options.format in UNCALIBRATED_FORMATS:
        return _run_mcap(options, leftovers, progress, start)
    with open_take(options.take) as take:
        if take.time_domain != "rig":
            raise TakeError(f"{take.path}: not on the rig timebase (time domain {take.time_domain})")
        if not take.cameras:
            raise TakeError(f"{take.path}: no RGB camera to export")
        cameras = cameras_of(take, options.resize)
        frames = frame_table(take, take.cameras)
        check_sizes(options, take, frames)
        test_camera_positions(options, take.cameras)
        staging = Staging(options.out, leftovers, {"take": str(take.path), "format": options.format})
        with _committed(options, staging):
            result = _write(options, take, cameras, frames, staging.dir, progress, start)
    log.info("exported %s as %s to %s in %.1f s", options.take, options.format, options.out, result.wall_s)
    return result


def _run_mcap(
    options: ExportOptions, leftovers: list[Path], progress: ProgressCallback, start: float
) -> ExportResult:
    """`--format mcap`: every stored stream of the take as ROS 2 messages in `<take_id>.mcap`."""
    from rigd.products.ros.mcap_export import write_mcap

    with open_take(options.take) as take:
        if take.time_domain != "rig":
            raise TakeError(f"{take.path}: not on the rig timebase (time domain {take.time_domain})")
        staging = Staging(options.out, leftovers, {"take": str(take.path), "format": options.format})
        with _committed(options, staging):
            stats = write_mcap(
                take,
                staging.dir / f"{take.take_id}.mcap",
                epoch=options.ros_epoch,
                slice_us=options.ros_slice_us,
                compressed=options.compressed,
                compression=options.ros_compression,
                progress=progress,
            )
            pulses = take.pulses()
            spans = [s for s in (take.sensor(n).span for n in take.event_sensors) if s is not None]
            result = ExportResult(
                take=str(take.path),
                take_id=take.take_id,
                format=options.format,
                out=str(options.out),
                timesteps=len(pulses),
                cameras=take.cameras,
                train=0,
                test=0,
                split="none",
                test_cameras=[],
                world="rig",
                rig_to_world=np.eye(4).tolist(),
                event_sensors=take.event_sensors,
                t0_us=min((s[0] for s in spans), default=0),
                t1_us=max((s[1] for s in spans), default=0),
                wall_s=round(time.perf_counter() - start, 3),
                bytes=_disk_bytes(staging.dir),
            )
            doc = {**result.model_dump(), "epoch_ns": stats.epoch_ns, "messages": stats.messages}
            (staging.dir / "export.json").write_text(json.dumps(doc, indent=2))
    log.info("exported %s as mcap to %s in %.1f s", options.take, options.out, result.wall_s)
    return result


def _write(
    options: ExportOptions,
    take: Take,
    cameras: list[Camera],
    frames: FrameTable,
    out: Path,
    progress: ProgressCallback,
    start: float,
) -> ExportResult:
    """Every file of the export under `out` (the staging directory), export.json last."""
    plan = ExportPlan(options=options, take=take, cameras=cameras, frames=frames, progress=progress, out=out)
    apply_world(plan)
    train = plan.train_mask
    progress(ProgressUpdate("images", f"0/{plan.images()} frames", 0, plan.images()))
    writer = {
        "dynamic3dgs": dynamic3dgs.write,
        "4dgaussians": dynamic3dgs.write,
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
        train=int(train.sum()),
        test=int((~train).sum()),
        split=options.split_kind,
        test_cameras=[cameras[j].name for j in plan.test_cameras] if options.split_kind == "camera" else [],
        world=plan.world_note,
        rig_to_world=plan.rig_to_world.tolist(),
        event_sensors=take.event_sensors,
        t0_us=frames.t0_us,
        t1_us=frames.t1_us,
        wall_s=round(time.perf_counter() - start, 3),
        bytes=_disk_bytes(out),
    )
    (out / "export.json").write_text(json.dumps(result.model_dump(), indent=2))
    return result
