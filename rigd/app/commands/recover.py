"""`rigd recover`: seal takes whose writer crashed; one line per take.

Register with `app.command("recover")(recover_command)`. Arguments are take files or
directories (every unfinished take in them). A file that cannot be read or sealed is one
ERROR line naming it and why (an entry with `error` in --json), and the others are still
sealed. Exit code 0 when every take is sealed (complete, or failed with a reason when no rig
time could be fitted) or needed nothing; 1 when any file could not be handled (held by a
live writer, unreadable); 2 when no take was named or found, or a directory cannot be listed.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.console import Console
from rich.markup import escape

from rigd.app.commands.consoles import fail, stderr_console, stdout_console
from rigd.core.errors import TakeError

if TYPE_CHECKING:  # the take file (h5py) loads when the command runs
    from rigd.take.recover import RecoveryReport
    from rigd.take.recover_dir import RecoveryProblem

log = logging.getLogger(__name__)
_err = stderr_console()
_COLOURS = {
    "sealed": "green",
    "would_seal": "green",
    "not_needed": "dim",
    "sealed_failed": "yellow",
    "would_seal_failed": "yellow",
    "in_use": "bold red",
}


def _take_dir(config: Path | None) -> Path:
    """The take directory a rig config names (the sim rig's when none is given)."""
    from rigd.app.config import RigConfig, default_sim_rig
    from rigd.core.errors import RigdError

    try:
        rig = RigConfig.load(config) if config is not None else default_sim_rig()
    except RigdError as exc:
        raise fail(exc) from exc
    return rig.service.take_dir


def _recover_all(paths: list[Path], *, dry_run: bool) -> list[RecoveryReport | RecoveryProblem]:
    """Files as given, directories expanded to their unfinished takes; a file that cannot be
    read or sealed is a `RecoveryProblem` in the list, never the end of the run."""
    from rigd.app.capture.ballast import remove_stale_ballast
    from rigd.take.recover_dir import recover_dir, recover_one

    out: list[RecoveryReport | RecoveryProblem] = []
    for p in paths:
        if p.is_dir():
            out.extend(recover_dir(p, dry_run=dry_run))
        else:
            out.append(recover_one(p, dry_run=dry_run))
        if not dry_run:  # the disk ballast a killed capture left next to its take
            remove_stale_ballast(p if p.is_dir() else p.parent)
    return out


def recover_command(
    paths: Annotated[
        list[Path] | None,
        typer.Argument(
            help="Take files, or directories to search for unfinished takes (default: the rig "
            "config's service.take_dir)."
        ),
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option("--config", "-c", help="Rig config whose take_dir to search (default: the sim rig's)."),
    ] = None,
    dry_run: Annotated[
        bool, typer.Option("--dry-run", help="Report what would be trimmed and sealed; change nothing.")
    ] = False,
    json_out: Annotated[bool, typer.Option("--json", help="Print the recovery reports as JSON.")] = False,
) -> None:
    """Repair and seal takes left unfinished by a crash (status recording, or a cut-short finalize)."""
    if not paths:
        take_dir = _take_dir(config)
        if not take_dir.is_dir():
            _err.print(f"no take directory {escape(str(take_dir))}: nothing to recover", soft_wrap=True)
            raise typer.Exit(code=0)
        paths = [take_dir]
        _err.print(f"searching {escape(str(take_dir))} for unfinished takes", soft_wrap=True)
    try:
        results = _recover_all(paths, dry_run=dry_run)
    except TakeError as exc:  # a directory that cannot be listed
        raise fail(exc) from exc
    if not results:
        _err.print("no unfinished takes found")
        raise typer.Exit(code=0 if paths and all(p.is_dir() for p in paths) else 2)
    from rigd.take.recover_dir import RecoveryProblem

    ok = True
    out = stdout_console(highlight=False)
    for r in results:
        if isinstance(r, RecoveryProblem):
            ok = False
            if not json_out:  # the one message about it, where errors go
                _err.print(f"[bold red]{'ERROR':<17}[/] {escape(r.line())}", soft_wrap=True, highlight=False)
            continue
        ok &= r.sealed
        if not json_out:
            _print(out, r)
    if json_out:
        typer.echo(json.dumps([r.model_dump(mode="json") for r in results], indent=2))
    if not ok:
        raise typer.Exit(code=1)


def _print(out: Console, rr: RecoveryReport) -> None:
    colour = _COLOURS[rr.outcome]
    out.print(f"[{colour}]{rr.outcome.upper():<17}[/] {escape(rr.line())}")
    for t in rr.trims:
        before = ", ".join(f"{k}={v}" for k, v in t.lengths_before.items())
        out.print(f"    trimmed {escape(t.hpath)} to {t.after} ({before}): {escape(t.reason)}")
