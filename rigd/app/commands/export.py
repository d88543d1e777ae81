"""`rigd export TAKE --format F --out DIR`: a calibrated take as a trainer's or event loader's input.

Parses the arguments into `ExportOptions`, runs `rigd.products.export.run_export` under a rich
progress bar (on a terminal: frames, grids or events written / total of the current stage) and
prints one summary line. A refused input (bad knob, a size over its bound, an `--out` that cannot
take the export) is one line on stderr and exit code 2; a failed write (disk full) is one line and
exit code 1, with the partial output removed.
Register with `app.command("export")(export)`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from pydantic import ValidationError
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TaskID, TextColumn, TimeRemainingColumn

from rigd.app.commands.consoles import fail, stderr_console
from rigd.core.errors import ConfigError, RigdError
from rigd.core.progress import ProgressUpdate

#: rigd.products.export.FORMATS, spelled out so that `--help` need not import the exporters (h5py,
#: OpenCV); tests/app/commands/test_lazy_imports.py holds the two equal.
EXPORT_FORMATS = ("dynamic3dgs", "4dgaussians", "nerfstudio", "colmap", "dsec", "mcap")
#: rigd.products.export.WORLDS and SPLITS, spelled out for the same reason.
EXPORT_WORLDS = ("board", "cam0", "floor")
EXPORT_SPLITS = ("time", "camera")

_err = stderr_console()


def _slice_us(text: str) -> int:
    try:
        ms = int(text)
    except ValueError:
        raise ConfigError(f"--ros-slice-ms {text!r}: not an integer") from None
    if ms < 0:
        raise ConfigError(f"--ros-slice-ms {ms}: must be 0 or more")
    return ms * 1000


def export(
    take: Annotated[Path, typer.Argument(help="Take file (.h5) with a stored calibration.")],
    fmt: Annotated[str, typer.Option("--format", "-f", help=f"One of: {', '.join(EXPORT_FORMATS)}.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output directory (created; parent must exist).")],
    resize: Annotated[
        str | None, typer.Option("--resize", help="Output image size WxH (e.g. 1280x720); K is scaled.")
    ] = None,
    segments: Annotated[
        Path | None,
        typer.Option("--segments", help="`rigd reconstruct --out` directory: carry its segments/keyframes."),
    ] = None,
    voxel_bins: Annotated[
        str, typer.Option("--voxel-bins", metavar="INT", help="Time bins of the event voxel grids.")
    ] = "5",
    seg: Annotated[
        bool,
        typer.Option("--seg", help="Kept for old command lines: dynamic3dgs always writes its seg/ masks."),
    ] = False,
    world: Annotated[
        str | None,
        typer.Option(
            "--world",
            help=f"World frame: {', '.join(EXPORT_WORLDS)} (default floor for dynamic3dgs, cam0 otherwise).",
        ),
    ] = None,
    split: Annotated[
        str | None,
        typer.Option(
            "--split",
            help=f"Held-out views: {', '.join(EXPORT_SPLITS)} "
            "(default camera for dynamic3dgs and 4dgaussians).",
        ),
    ] = None,
    test_camera: Annotated[
        list[str] | None,
        typer.Option(
            "--test-camera", help="--split camera: a held-out camera (repeat; default the middle one)."
        ),
    ] = None,
    force: Annotated[
        bool,
        typer.Option("--force", help="Replace an earlier export at --out (or what an interrupted one left)."),
    ] = False,
    ros_epoch: Annotated[
        str,
        typer.Option(
            "--ros-epoch",
            help="mcap: header stamps are rig time plus the take's creation second (take) or rig time (rig).",
        ),
    ] = "take",
    ros_slice_ms: Annotated[
        str,
        typer.Option(
            "--ros-slice-ms",
            metavar="INT",
            help="mcap: event packets of at least this span (0: one per block).",
        ),
    ] = "0",
    compressed: Annotated[
        bool, typer.Option("--compressed", help="mcap: frames as lossless PNG sensor_msgs/CompressedImage.")
    ] = False,
    ros_compression: Annotated[
        str, typer.Option("--ros-compression", help="mcap: chunk compression zstd, lz4 or none.")
    ] = "zstd",
) -> None:
    """Export a calibrated take for a 4D reconstruction trainer (dynamic3dgs, nerfstudio, colmap),
    for event loaders (dsec), or any take as ROS 2 messages in MCAP (mcap); see docs/export.md."""
    from rigd.products.export import (
        FORMATS,
        SPLITS,
        WORLDS,
        ExportOptions,
        ExportWriteError,
        parse_count,
        parse_size,
        run_export,
    )

    try:
        if fmt not in FORMATS:
            raise ConfigError(f"--format {fmt!r}: unknown format (one of {', '.join(FORMATS)})")
        if world is not None and world not in WORLDS:
            raise ConfigError(f"--world {world!r}: unknown world frame (one of {', '.join(WORLDS)})")
        if split is not None and split not in SPLITS:
            raise ConfigError(f"--split {split!r}: unknown split (one of {', '.join(SPLITS)})")
        options = ExportOptions(
            take=take,
            format=fmt,
            out=out,
            resize=parse_size(resize) if resize else None,
            segments=segments,
            voxel_bins=parse_count("--voxel-bins", voxel_bins),
            seg=seg,
            world=world,
            split=split,
            test_cameras=tuple(test_camera or ()),
            force=force,
            ros_epoch=ros_epoch,
            ros_slice_us=_slice_us(ros_slice_ms),
            compressed=compressed,
            ros_compression=ros_compression,
        )
    except ValidationError as exc:
        err = exc.errors()[0]
        where, why = "-".join(str(p) for p in err["loc"]).replace("_", "-"), str(err["msg"])
        raise fail(f"--{where}: {why}" if where else why.removeprefix("Value error, ")) from exc
    except RigdError as exc:
        raise fail(str(exc)) from exc
    with Progress(
        TextColumn("[bold]{task.description}[/]"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=_err,
        disable=not _err.is_terminal,
    ) as progress:
        tasks: dict[str, TaskID] = {}

        def advance(update: ProgressUpdate) -> None:
            if update.stage not in tasks:
                tasks[update.stage] = progress.add_task(update.stage, total=update.total)
            progress.update(tasks[update.stage], completed=update.done or 0, total=update.total)

        try:
            result = run_export(options, advance)
        except ExportWriteError as exc:
            raise fail(str(exc), code=1) from exc
        except RigdError as exc:
            raise fail(str(exc)) from exc
    if result.format == "mcap":
        _err.print(
            f"{result.take_id} -> {result.out} (mcap): {len(result.cameras)} cameras, "
            f"{len(result.event_sensors)} event sensors, {result.timesteps} pulses, "
            f"{result.bytes / 1e6:.1f} MB in {result.wall_s:.1f} s",
            soft_wrap=True,
            highlight=False,
        )
        return
    _err.print(
        f"{result.take_id} -> {result.out} ({result.format}): {result.timesteps} timesteps x "
        f"{len(result.cameras)} cameras ({result.train} train / {result.test} test views, split by "
        f"{result.split}), "
        f"{len(result.event_sensors)} event sensors, {result.bytes / 1e6:.1f} MB in {result.wall_s:.1f} s",
        soft_wrap=True,
        highlight=False,
    )
