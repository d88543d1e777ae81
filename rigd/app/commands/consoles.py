"""The rich consoles commands print through: as wide as the terminal on a terminal, and off one
(a pipe, a file, the journal) wide enough that nothing is wrapped or cut.

Rich assumes 80 columns when it cannot ask a terminal, which splits a URL or a path in the middle
and cuts table cells to `trigg...`; what a script or a log reads must hold the whole text.
"""

from __future__ import annotations

import typer
from rich.console import Console
from rich.markup import escape

#: Columns of a console that is not a terminal: no line or table of rigd's is this wide, so none
#: is wrapped or truncated (a table is only as wide as its cells).
OFF_TERMINAL_WIDTH = 4096


def _console(stderr: bool, highlight: bool) -> Console:
    probe = Console(stderr=stderr, highlight=highlight)
    if probe.is_terminal:
        return probe
    return Console(stderr=stderr, highlight=highlight, width=OFF_TERMINAL_WIDTH, soft_wrap=True)


def stdout_console(*, highlight: bool = True) -> Console:
    """A console on stdout (results, tables, JSON)."""
    return _console(stderr=False, highlight=highlight)


def stderr_console(*, highlight: bool = True) -> Console:
    """A console on stderr (progress, warnings, errors)."""
    return _console(stderr=True, highlight=highlight)


def fail(error: Exception | str, code: int = 2) -> typer.Exit:
    """Say `error` on stderr as the commands' one error line and return the exit to raise
    (`raise fail(exc) from None`); the message is printed as text, never as rich markup."""
    stderr_console().print(f"[bold red]error:[/] {escape(str(error))}", soft_wrap=True, highlight=False)
    return typer.Exit(code=code)
