"""`rigd export TAKE --format F --out DIR`: a calibrated take as a trainer's or event loader's input.

Parses the arguments into `ExportOptions`, runs `rigd.app.export.run_export` under a rich
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
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TaskID, TextColumn, TimeRemainingColumn

from rigd.app.commands.consoles import stderr_console
from rigd.app.workflows.progress import ProgressUpdate
from rigd.core.errors import ConfigError, RigdError

#: rigd.app.export.FORMATS, spelled out so that `--help` need not import the exporters (h5py,
#: OpenCV); tests/app/commands/test_lazy_imports.py holds the two equal.
EXPORT_FORMATS = ("dynamic3dgs", "nerfstudio", "colmap", "dsec")

_err = stderr_console()


def _fail(message: str, code: int = 2) -> typer.Exit:
    _err.print(f"[bold red]error:[/] {escape(message)}", soft_wrap=True, highlight=False)
    return typer.Exit(code=code)


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
        typer.Option("--seg", help="dynamic3dgs: write all-foreground seg/ masks (its train.py reads them)."),
    ] = False,
    force: Annotated[
        bool,
        typer.Option("--force", help="Replace an earlier export at --out (or what an interrupted one left)."),
    ] = False,
) -> None:
    """Export a calibrated take for a 4D reconstruction trainer (dynamic3dgs, nerfstudio, colmap)
    or for event loaders (dsec); see docs/export.md."""
    from rigd.app.export import FORMATS, ExportOptions, ExportWriteError, parse_count, parse_size, run_export

    try:
        if fmt not in FORMATS:
            raise ConfigError(f"--format {fmt!r}: unknown format (one of {', '.join(FORMATS)})")
        options = ExportOptions(
            take=take,
            format=fmt,
            out=out,
            resize=parse_size(resize) if resize else None,
            segments=segments,
            voxel_bins=parse_count("--voxel-bins", voxel_bins),
            seg=seg,
            force=force,
        )
    except ValidationError as exc:
        err = exc.errors()[0]
        raise _fail(f"--{'-'.join(str(p) for p in err['loc']).replace('_', '-')}: {err['msg']}") from exc
    except RigdError as exc:
        raise _fail(str(exc)) from exc
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
            raise _fail(str(exc), code=1) from exc
        except RigdError as exc:
            raise _fail(str(exc)) from exc
    _err.print(
        f"{result.take_id} -> {result.out} ({result.format}): {result.timesteps} timesteps x "
        f"{len(result.cameras)} cameras ({result.train} train / {result.test} test), "
        f"{len(result.event_sensors)} event sensors, {result.bytes / 1e6:.1f} MB in {result.wall_s:.1f} s",
        soft_wrap=True,
        highlight=False,
    )
