"""`rigd reconstruct TAKE... --out DIR`: denoise, segment, keyframes and snapshots per take.

Parses the arguments into `ReconstructOptions` (every knob, the paper's values as defaults; the
outputs are described in `rigd.products.reconstruct`), shows progress per stage in its own
unit with the time left (`StageProgress`: a bar on a terminal, a line per stage with `rigd -v`
otherwise) and prints one line per take with its rate; exit code 1 when any take failed.
Register with `app.command("reconstruct")(reconstruct)`.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from pydantic import ValidationError
from rich.markup import escape

from rigd.app.commands.consoles import fail, stderr_console
from rigd.app.commands.progress import StageProgress
from rigd.core.errors import ConfigError, RigdError

if TYPE_CHECKING:  # the pipeline (dask, numba, h5py) loads when the command runs
    from rigd.products.reconstruct_options import ReconstructOptions, TakeReconstruction

#: rigd.products.reconstruct_scheduler.LOCAL_SCHEDULERS, spelled out so that `--help` need not import
#: the pipeline; tests/app/commands/test_lazy_imports.py holds the two equal.
LOCAL_SCHEDULER_NAMES = ("threads", "processes", "sync")

_err = stderr_console()


def _line(r: TakeReconstruction) -> str:
    parts = [f"{r.segments} segment{'s' if r.segments != 1 else ''}"]
    for sensor, s in r.sensors.items():
        share = f" ({100 * s.events_kept / s.events_in:.1f} %)" if s.events_in else ""
        parts.append(f"{sensor} kept {s.events_kept:,} of {s.events_in:,} events{share}")
    n = sum(s.events_in for s in r.sensors.values())
    rate = f", {n / r.seconds / 1e6:.2f} Mev/s" if r.seconds > 0 else ""
    return f"{r.take}: " + "; ".join(parts) + f" in {r.seconds:.1f} s{rate}"


def reconstruct(
    takes: Annotated[list[Path], typer.Argument(help="Take files (.h5).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output directory.")],
    scheduler: Annotated[
        str,
        typer.Option(
            "--scheduler",
            help=f"Dask scheduler: {', '.join(LOCAL_SCHEDULER_NAMES)} (local), or a dask.distributed address "
            "(tcp://HOST:PORT).",
        ),
    ] = "threads",
    workers: Annotated[
        int | None, typer.Option("--workers", min=1, help="Local workers (default: one per core).")
    ] = None,
    no_filter: Annotated[
        bool, typer.Option("--no-filter", help="Skip the background-activity filter.")
    ] = False,
    filter_window_us: Annotated[
        int, typer.Option("--filter-window-us", min=1, help="Filter: support window, us (paper: 30).")
    ] = 30,
    filter_radius: Annotated[
        int,
        typer.Option("--filter-radius", min=1, max=8, help="Filter: neighbourhood radius, px (paper: 3)."),
    ] = 3,
    filter_support: Annotated[
        int,
        typer.Option("--filter-support", min=0, help="Filter: same-polarity neighbours needed (paper: 2)."),
    ] = 2,
    threshold: Annotated[
        float,
        typer.Option(
            "--threshold", min=0.0, help="Partition: activity budget per segment, kept events per pixel."
        ),
    ] = 2.0,
    partition_window_us: Annotated[
        int, typer.Option("--partition-window-us", min=100, help="Partition: activity window, us.")
    ] = 5_000,
    instant_weight: Annotated[
        float, typer.Option("--instant-weight", min=0.0, help="Partition: weight of one window's activity.")
    ] = 1.0,
    min_segment_us: Annotated[
        int, typer.Option("--min-segment-us", min=0, help="Partition: shortest segment, us.")
    ] = 10_000,
    map_scale: Annotated[
        float, typer.Option("--map-scale", min=0.01, max=1.0, help="Keyframe maps: resolution scale.")
    ] = 0.25,
    max_candidates: Annotated[
        int,
        typer.Option("--max-candidates", min=0, help="Keyframe candidates per segment at most (0: all)."),
    ] = 256,
    keyframe_camera: Annotated[
        str | None,
        typer.Option("--keyframe-camera", help="Camera whose mid-exposure times are the candidates."),
    ] = None,
    e2i: Annotated[
        str, typer.Option("--e2i", help="Snapshots: highpass (paper-style) or direct integration.")
    ] = "highpass",
    contrast: Annotated[
        float, typer.Option("--contrast", min=0.0, help="Snapshots: contrast, log units.")
    ] = 0.3,
    cutoff_hz: Annotated[
        float, typer.Option("--cutoff-hz", min=0.0, help="Snapshots: high-pass cutoff, Hz.")
    ] = 5.0,
) -> None:
    """Denoise, segment the rig's sequence by motion, choose keyframes and reconstruct snapshots per take."""
    from rigd.products.reconstruct_options import ReconstructOptions
    from rigd.products.reconstruct_tasks import FilterKnobs

    for take in takes:  # one line naming the path, whole (typer's own check wraps it in a box)
        if not take.exists():
            raise fail(ConfigError(f"{take}: no such take file"))
        if take.is_dir():
            raise fail(ConfigError(f"{take}: is a directory, not a take file"))
    try:
        filt = FilterKnobs(
            enabled=not no_filter,
            window_us=filter_window_us,
            radius_px=filter_radius,
            min_support=filter_support,
        )
        # One keyword per flag; alike in shape to the other commands' option models, nothing shared.
        options = ReconstructOptions(
            takes=takes,
            out=out,
            scheduler=scheduler,
            workers=workers,
            filter=filt,
            threshold=threshold,
            partition_window_us=partition_window_us,
            instant_weight=instant_weight,
            min_segment_us=min_segment_us,
            map_scale=map_scale,
            max_candidates=max_candidates,
            keyframe_camera=keyframe_camera,
            e2i=e2i,
            contrast=contrast,
            cutoff_hz=cutoff_hz,
        )
    except ValidationError as exc:
        err = exc.errors()[0]
        name = str(err["loc"][-1]) if err["loc"] else ""
        flag = _FILTER_FLAGS.get(name, "--" + name.replace("_", "-"))
        msg = str(err["msg"]).removeprefix("Value error, ")
        raise fail(f"{flag}: {msg}") from None
    _run(options)


#: FilterKnobs fields by the flag that sets them.
_FILTER_FLAGS = {
    "window_us": "--filter-window-us",
    "radius_px": "--filter-radius",
    "min_support": "--filter-support",
}


def _run(options: ReconstructOptions) -> None:
    from rigd.products.reconstruct import run_reconstruct

    try:
        with StageProgress(_err, "reconstruct") as progress:
            results = run_reconstruct(options, progress)
    except RigdError as exc:  # the scheduler (a take's own failure is in its result)
        raise fail(exc) from None
    for r in results:
        if r.error is not None:
            _err.print(f"[bold red]error:[/] {escape(r.error)}", soft_wrap=True, highlight=False)
        else:
            _err.print(escape(_line(r)), soft_wrap=True, highlight=False)
    if any(r.error is not None for r in results):
        raise typer.Exit(code=1)
