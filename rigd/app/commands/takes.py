"""`rigd takes [DIR]`: the takes in a directory, oldest first: name, verdict, length, devices, size;
`rigd takes gather TAKE.h5`: a multi-host take's parts copied from their hosts and joined again.

Register with `app.add_typer(takes_app, name="takes")`. Listing exits 0 (an empty directory is an
answer), 2 when the directory cannot be listed. A file that is not a readable take is listed
with why.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.markup import escape
from rich.table import Table

from rigd.app.commands.consoles import stderr_console, stdout_console
from rigd.app.commands.help import RigdGroup, RigdTyper
from rigd.core.errors import RigdError

if TYPE_CHECKING:
    from typer._click.core import Context

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
        if r.part_of is not None:
            text += f" [dim](host {escape(r.part_host or '?')}'s part of {escape(r.part_of)})[/]"
        elif r.parts:
            text += f" [dim]({len(r.parts)} host parts)[/]"
        length = "-" if r.duration_s is None else f"{r.duration_s:.1f} s"
        table.add_row(escape(r.name), text, length, escape(_devices(r)), _size(r.size_bytes + r.parts_bytes))
    stdout_console().print(table)


def gather(
    take: Annotated[Path, typer.Argument(help="The joined multi-host take (<stem>.h5) to complete.")],
    config: Annotated[
        Path | None,
        typer.Option(
            "--config",
            "-c",
            help="Rig config whose `hosts` give each host's endpoint and keys (default: the take's).",
        ),
    ] = None,
    json_out: Annotated[
        bool, typer.Option("--json", help="What was done per host and the verdict, as JSON.")
    ] = False,
    timeout: Annotated[
        float, typer.Option("--timeout", min=0.1, help="Seconds each request to a host may take.")
    ] = 30.0,
) -> None:
    """Copy a multi-host take's missing or changed parts from their hosts (resumable, checked
    by sha256), then join the take again. Exit 0 when every part is in, 1 when some are not."""
    from rigd.app.config import RigConfig
    from rigd.app.take_gather import gather_take, hosts_of_take

    try:
        hosts = RigConfig.load(config).hosts if config is not None else hosts_of_take(take)
        result = gather_take(take, hosts, timeout_s=timeout)
    except (RigdError, OSError) as exc:
        _err.print(f"[bold red]error:[/] {escape(str(exc))}", soft_wrap=True, highlight=False)
        raise typer.Exit(code=2) from exc
    join = result.join
    assert join is not None
    if json_out:
        body = {
            "take": str(take),
            "actions": result.actions,
            "parts": [p.model_dump(mode="json") for p in join.parts],
            "verdict": join.verdict.model_dump(mode="json"),
        }
        typer.echo(json.dumps(body, indent=2))
    else:
        out = stdout_console()
        for host, action in result.actions.items():
            out.print(f"{escape(host)}: {escape(action)}", soft_wrap=True, highlight=False)
        out.print(f"{escape(str(take))}: {escape(join.verdict.line())}", soft_wrap=True, highlight=False)
    if join.missing_devices:
        raise typer.Exit(code=1)


class TakesGroup(RigdGroup):
    """`rigd takes [DIR]` lists a directory (the `list` command, the default); `rigd takes
    gather TAKE.h5` completes a multi-host take."""

    def parse_args(self, ctx: Context, args: list[str]) -> list[str]:
        if not args or (args[0] not in self.commands and args[0] not in ("--help", "-h")):
            args = ["list", *args]
        return super().parse_args(ctx, args)


takes_app = RigdTyper(cls=TakesGroup, help="The takes in a directory; `gather` completes a multi-host take.")
takes_app.command("list")(takes)
takes_app.command("gather")(gather)
