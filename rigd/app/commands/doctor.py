"""`rigd doctor`: check this machine against the rig config; one line per check with the fix.

Register with `app.command("doctor")(doctor)`. Exit code 0 when nothing FAILs (WARNs are
advice), 1 when a check FAILs, 2 when the rig config cannot be loaded.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from rigd.app.commands.consoles import stderr_console, stdout_console
from rigd.core.errors import RigdError

_err = stderr_console()
_COLOURS = {"OK": "green", "WARN": "yellow", "FAIL": "bold red"}


def doctor(
    config: Annotated[
        Path | None, typer.Option("--config", "-c", help="Rig config to check rates, disk and backends for.")
    ] = None,
    out_dir: Annotated[Path, typer.Option("--out", "-o", help="Where takes will be written.")] = Path(
        "takes"
    ),
    duration: Annotated[float, typer.Option("--duration", help="Planned take length in seconds.")] = 600.0,
    disk_test: Annotated[
        bool, typer.Option("--disk-test/--no-disk-test", help="Measure disk write speed (writes 64 MiB).")
    ] = True,
    trigger_test: Annotated[
        bool,
        typer.Option(
            "--trigger-test/--no-trigger-test",
            help="With --config: open the trigger box and let it send 10 pulses (the devices on its "
            "line see them); checks its identity, its schedule and its counters.",
        ),
    ] = True,
    json_out: Annotated[bool, typer.Option("--json", help="Print the checks as JSON.")] = False,
) -> None:
    """Check permissions, USB links, usbfs, disk, clocks, buffers and backends; suggest fixes."""
    from rigd.app.config import RigConfig
    from rigd.app.doctor import checks_to_dict, run_checks, summary_status

    try:
        rig = RigConfig.load(config) if config is not None else None
    except RigdError as exc:
        _err.print(f"[bold red]error:[/] {exc}")
        raise typer.Exit(code=2) from exc
    checks = run_checks(
        rig=rig, out_dir=out_dir, duration_s=duration, disk_test=disk_test, trigger_test=trigger_test
    )
    if json_out:
        typer.echo(json.dumps(checks_to_dict(checks), indent=2))
    else:
        out = stdout_console(highlight=False)
        for c in checks:
            out.print(f"[{_COLOURS[c.status]}]{c.status:<4}[/] {escape(c.name)}: {escape(c.message)}")
            if c.fix and c.status != "OK":
                out.print(f"     -> {escape(c.fix)}")
        out.print(f"overall: {summary_status(checks)}")
    if summary_status(checks) == "FAIL":
        raise typer.Exit(code=1)
