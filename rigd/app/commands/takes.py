"""`rigd takes [DIR]`: the takes in a directory, oldest first: name, verdict, length, devices, size.

Register with `app.command("takes")(takes)`. Exit code 0 (an empty directory is an answer), 2 when
the directory cannot be listed. A file that is not a readable take is listed with why.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.markup import escape
from rich.table import Table

from rigd.app.commands.consoles import stderr_console, stdout_console
from rigd.core.errors import RigdError

if TYPE_CHECKING:
    from rigd.app.take_list import TakeRow

_err = stderr_console()
_VERDICT_STYLE = {
    "complete": "green",
    "degraded": "yellow",
    "failed": "bold red",
    "unfinished": "bold red",
    "damaged": "bold red",
}


def _size(n: int) -> str:
    return f"{n / 1e9:.2f} GB" if n >= 1e9 else f"{n / 1e6:.1f} MB"


def _devices(row: TakeRow) -> str:
    return ", ".join([*row.cameras, *row.event_sensors]) or "-"


def takes(
    directory: Annotated[
        Path | None,
        typer.Argument(help="Directory of takes (default: the rig config's service.take_dir)."),
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option("--config", "-c", help="Rig config whose take_dir to list (default: the sim rig's)."),
    ] = None,
    json_out: Annotated[bool, typer.Option("--json", help="One JSON object per take, in a list.")] = False,
) -> None:
    """List the takes in a directory: name, verdict (and why), length, devices, size."""
    from rigd.app.config import RigConfig, default_sim_rig
    from rigd.app.take_list import list_takes

    try:
        if directory is None:
            rig = RigConfig.load(config) if config is not None else default_sim_rig()
            directory = rig.service.take_dir
        rows = list_takes(directory)
    except RigdError as exc:
        _err.print(f"[bold red]error:[/] {escape(str(exc))}", soft_wrap=True, highlight=False)
        raise typer.Exit(code=2) from exc
    if json_out:
        typer.echo(json.dumps([r.model_dump(mode="json") for r in rows], indent=2))
        return
    if not rows:
        _err.print(f"no takes in {escape(str(directory))}", soft_wrap=True, highlight=False)
        return
    table = Table("take", "verdict", "length", "devices", "size", title=str(directory), title_justify="left")
    # The name is what a person copies into the next command: never cut, on a narrow terminal too
    # (the devices and the verdict's reason wrap instead).
    table.columns[0].min_width = max(len(r.name) for r in rows)
    table.columns[0].no_wrap = True
    for r in rows:
        if r.error is not None:
            what = "[bold red]damaged[/]" if r.verdict == "damaged" else "[bold red]unreadable[/]"
            table.add_row(escape(r.name), what, "-", escape(r.error), _size(r.size_bytes))
            continue
        verdict = r.verdict or r.status or "?"
        style = _VERDICT_STYLE.get(verdict, "")
        text = f"[{style}]{verdict}[/]" if style else verdict
        if r.reason:
            text += f": {escape(r.reason)}"
        length = "-" if r.duration_s is None else f"{r.duration_s:.1f} s"
        table.add_row(escape(r.name), text, length, escape(_devices(r)), _size(r.size_bytes))
    stdout_console().print(table)
