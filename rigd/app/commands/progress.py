"""Progress of a long command on the terminal: one stage at a time, each counted in its own unit
(pulses, queued items, frames reconstructed, views detected) with the time it has left.

A bar that counted one unit through the whole run would sit full while the rest happens, so every
stage starts its own count. Where stderr is not a terminal (a pipe, a journal, a test) there is no
bar; with `rigd -v` each stage is one line instead, so what a command was doing is on record, and
without it the output stays what scripts read (a failure is its one error line).
"""

from __future__ import annotations

import logging
import math
from types import TracebackType
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, Progress, ProgressColumn, Task, TaskID, TextColumn
from rich.text import Text

from rigd.core.progress import ProgressUpdate


class CountColumn(ProgressColumn):
    """`done/total` for a counted stage, `done` alone for an open-ended one, nothing for one with no
    count at all (rich's own column shows `0/?`)."""

    def render(self, task: Task) -> Text:
        if task.total is not None:
            return Text(f"{int(task.completed):,}/{int(task.total):,}", style="progress.download")
        return Text(f"{int(task.completed):,}" if task.completed else "", style="progress.download")


class TimeLeftColumn(ProgressColumn):
    """The time a counted stage has left, from its rate so far; the time spent on an uncounted one."""

    def render(self, task: Task) -> Text:
        if task.total is None:
            return Text(f"{_span(task.elapsed or 0.0)} so far", style="progress.elapsed")
        if task.finished:
            return Text("done", style="progress.remaining")
        left = task.time_remaining
        if left is None or not math.isfinite(left):
            return Text("estimating time left", style="progress.remaining")
        return Text(f"about {_span(left)} left", style="progress.remaining")


def _span(seconds: float) -> str:
    s = max(0, round(seconds))
    return f"{s // 60} min {s % 60:02d} s" if s >= 60 else f"{s} s"


class StageProgress:
    """A stage-by-stage progress display for one command (a context manager).

    `stage()` starts a stage: its name, its total in `unit` (None: not countable) and a note;
    `advance_to()` moves the current stage's count. `quiet` shows nothing (a `--json` run);
    `lines` (off a terminal) prints a line per stage, by default when logging is at INFO (`-v`)."""

    def __init__(
        self, console: Console, title: str, *, quiet: bool = False, lines: bool | None = None
    ) -> None:
        self._console = console
        self._title = title
        self._live = not quiet and console.is_terminal
        if lines is None:
            lines = logging.getLogger().isEnabledFor(logging.INFO)
        self._lines = not quiet and not self._live and lines
        self._bar = Progress(
            TextColumn("[bold]{task.description}[/]"),
            BarColumn(),
            CountColumn(),
            TextColumn("{task.fields[unit]}  {task.fields[detail]}"),
            TimeLeftColumn(),
            console=console,
            disable=not self._live,
        )
        self._task: TaskID | None = None
        self._stage: tuple[str, str] | None = None

    def __enter__(self) -> StageProgress:
        self._bar.__enter__()
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._bar.__exit__(kind, exc, tb)

    def stage(self, name: str, total: int | None, unit: str, note: str = "") -> None:
        """Start a stage (a new count, a new time-left estimate)."""
        self._stage = (name, note)
        description = f"{self._title}: {name}"
        if self._task is not None:
            self._bar.update(self._task, visible=False)
        self._task = self._bar.add_task(description, total=total, unit=unit, detail=note)
        if self._lines:
            count = "" if total is None else f" ({total:,} {unit})"
            tail = f": {note}" if note else ""
            self._console.print(f"{description}{count}{tail}", soft_wrap=True, highlight=False)

    def advance_to(self, done: int | None, detail: str | None = None, total: int | None = None) -> None:
        """The current stage's count (and a note beside it; a new total where it grew)."""
        if self._task is None:
            return
        fields: dict[str, Any] = {"completed": done or 0}
        if detail is not None:
            fields["detail"] = detail
        if total is not None:
            fields["total"] = total
        self._bar.update(self._task, **fields)

    def __call__(self, update: ProgressUpdate) -> None:
        """A workflow's `ProgressCallback`: a new stage or message starts a stage."""
        if self._stage != (update.stage, update.message):
            unit = update.unit or ""
            self.stage(update.stage, update.total, unit, update.message)
        self.advance_to(update.done)
