"""What `capture` and `inspect` print about a take: its summary, verdict first, and the
`--strict` exit for a take that lost data."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated

import typer

from rigd.app.commands.consoles import stderr_console, stdout_console

if TYPE_CHECKING:
    from rigd.take.reader import TakeSummary

console = stderr_console()
out = stdout_console()

#: Exit code of `capture --strict` / `inspect --strict` for a take that is not complete
#: (degraded: it lost data; docs/take-format.md, *Verdict*).
STRICT_EXIT = 3

StrictOpt = Annotated[
    bool,
    typer.Option(
        "--strict",
        help=f"Exit {STRICT_EXIT} unless the take's verdict is complete (nothing lost: no loss record, "
        "missing pulse, dropped frame or silent device).",
    ),
]


def check_strict(path: str, verdict: str | None, reasons: list[str]) -> None:
    """`--strict`: one line and exit STRICT_EXIT unless the take holds everything."""
    if verdict == "complete":
        return
    from rigd.take.verdict import TakeVerdict

    why = (
        "unknown (the daemon did not say)"
        if verdict is None
        else TakeVerdict.model_validate({"verdict": verdict, "reasons": reasons}).line(
            limit=len(reasons) or 1
        )
    )
    console.print(
        f"--strict: take {path} is not complete: {why}", soft_wrap=True, markup=False, highlight=False
    )
    raise typer.Exit(code=STRICT_EXIT)


def print_summary(summary: TakeSummary, take_line: str | None = None) -> None:
    """The summary, its verdict line first; `take_line` (the take's path) goes right after it."""
    from rigd.products.inspect import summary_renderables

    parts = summary_renderables(summary)
    if take_line is not None:
        out.print(parts[0], soft_wrap=True, highlight=False)
        typer.echo(take_line)
        parts = parts[1:]
    for part in parts:
        out.print(part, soft_wrap=isinstance(part, str), highlight=False)
