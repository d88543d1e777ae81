"""Progress of a long workflow, for whoever shows it (a rich bar, a log line, a web socket)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class ProgressUpdate:
    """One step of a workflow: which stage, about what, and how far (when countable), in `unit`
    (frames reconstructed, images searched): a display counts each stage in its own unit."""

    stage: str
    message: str
    done: int | None = None
    total: int | None = None
    unit: str = ""


ProgressCallback = Callable[[ProgressUpdate], None]


def no_progress(update: ProgressUpdate) -> None:
    """The default callback: callers that show nothing need not pass one."""
