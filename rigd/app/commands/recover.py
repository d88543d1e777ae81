"""`rigd recover`: seal takes whose writer crashed; one line per take.

Register with `app.command("recover")(recover_command)`. Arguments are take files or
directories (every unfinished take in them). Exit code 0 when every take is sealed (complete,
or failed with a reason when no rig time could be fitted) or needed nothing; 1 when any take
could not be sealed (held by a live writer, unreadable); 2 when no take was named or found.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape

from rigd.core.errors import TakeError
from rigd.take.recover import RecoveryReport, find_unfinished, recover_take

log = logging.getLogger(__name__)
_err = Console(stderr=True)
_COLOURS = {
    "sealed": "green",
    "would_seal": "green",
    "not_needed": "dim",
    "sealed_failed": "yellow",
    "would_seal_failed": "yellow",
    "in_use": "bold red",
}


def _targets(paths: list[Path]) -> list[Path]:
    """Files as given; directories expanded to their unfinished takes."""
    out: list[Path] = []
    for p in paths:
        out.extend(find_unfinished(p) if p.is_dir() else [p])
    return out


def recover_command(
    paths: Annotated[
        list[Path], typer.Argument(help="Take files, or directories to search for unfinished takes.")
    ],
    dry_run: Annotated[
        bool, typer.Option("--dry-run", help="Report what would be trimmed and sealed; change nothing.")
    ] = False,
    json_out: Annotated[bool, typer.Option("--json", help="Print the recovery reports as JSON.")] = False,
) -> None:
    """Repair and seal takes left unfinished by a crash (status recording, or a cut-short finalize)."""
    try:
        targets = _targets(paths)
    except TakeError as exc:
        _err.print(f"[bold red]error:[/] {escape(str(exc))}")
        raise typer.Exit(code=2) from exc
    if not targets:
        _err.print("no unfinished takes found")
        raise typer.Exit(code=0 if paths and all(p.is_dir() for p in paths) else 2)
    results: list[dict[str, Any]] = []
    ok = True
    out = Console(width=200, highlight=False, soft_wrap=True)
    for path in targets:
        try:
            rr = recover_take(path, dry_run=dry_run)
        except TakeError as exc:  # not a readable take: say so and go on with the others
            log.error("recovering %s failed: %s", path, exc)
            ok = False
            results.append({"path": str(path), "error": str(exc)})
            if not json_out:
                out.print(f"[bold red]ERROR[/] {escape(str(exc))}")
            continue
        ok &= rr.sealed
        results.append(rr.model_dump(mode="json"))
        if not json_out:
            _print(out, rr)
    if json_out:
        typer.echo(json.dumps(results, indent=2))
    if not ok:
        raise typer.Exit(code=1)


def _print(out: Console, rr: RecoveryReport) -> None:
    colour = _COLOURS[rr.outcome]
    out.print(f"[{colour}]{rr.outcome.upper():<17}[/] {escape(rr.line())}")
    for t in rr.trims:
        before = ", ".join(f"{k}={v}" for k, v in t.lengths_before.items())
        out.print(f"    trimmed {escape(t.hpath)} to {t.after} ({before}): {escape(t.reason)}")
