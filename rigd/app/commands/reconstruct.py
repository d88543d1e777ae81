"""`rigd reconstruct TAKE... --out DIR [--scheduler ADDR]`: denoise, partition and snapshots per take.

Parses the arguments, runs `rigd.app.workflows.reconstruct` (the outputs are described there)
under a rich progress bar (on a terminal) and prints one line per take and sensor, or one line
per take that failed; exit code 1 when any did.
Register with `app.command("reconstruct")(reconstruct)`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import Progress

from rigd.app.workflows.progress import ProgressUpdate
from rigd.app.workflows.reconstruct import ReconstructOptions, run_reconstruct

_err = Console(stderr=True)


def reconstruct(
    takes: Annotated[list[Path], typer.Argument(help="Take files (.h5).", exists=True, dir_okay=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output directory.")],
    scheduler: Annotated[
        str | None, typer.Option("--scheduler", help="Dask distributed scheduler address; local if omitted.")
    ] = None,
) -> None:
    """Denoise, partition into motion-aware segments and reconstruct keyframe snapshots per take."""
    options = ReconstructOptions(takes=takes, out=out, scheduler=scheduler)
    with Progress(console=_err, transient=False, disable=not _err.is_terminal) as progress:
        bar = progress.add_task("reconstruct", total=len(takes))

        def advance(update: ProgressUpdate) -> None:
            progress.update(bar, completed=update.done)

        results = run_reconstruct(options, advance)
    for r in results:
        if r.error is not None:
            _err.print(f"[bold red]error:[/] {escape(r.error)}", soft_wrap=True, highlight=False)
        for sensor, s in r.sensors.items():
            _err.print(f"{r.take} {sensor}: {s.events_kept}/{s.events_in} events kept, {s.segments} segments")
    if any(r.error is not None for r in results):
        raise typer.Exit(code=1)
