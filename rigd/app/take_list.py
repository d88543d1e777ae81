"""The takes in a directory, one row each: what `rigd takes [DIR]` prints.

Each row comes from the take's metadata, the sync report and the frame times (`Take.summary`), not
from its frames or events, so a directory of multi-gigabyte takes lists in a moment. A file that
cannot be read is a row that says why, never the end of the listing.

A multi-host take is one row: the part files its manifest names are folded into it (their bytes
counted in its size). A part no take in the directory claims (on a host other than the
coordinator, or before the join) is listed as that host's part of its take.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

from pydantic import BaseModel, Field

from rigd.core.errors import RigdError, TakeError, TakeFormatError
from rigd.take.isolated import READ_TIMEOUT_S, run_isolated
from rigd.take.manifest import PART_NAME

log = logging.getLogger(__name__)

#: File names a take has (rigd.app.capture.new_take_path writes `.h5`).
TAKE_SUFFIXES = (".h5", ".hdf5")


class TakeRow(BaseModel):
    """One take as listed. `error` is set (and the rest mostly empty) when it could not be read."""

    path: str
    name: str
    status: str | None = None
    verdict: str | None = None
    reason: str | None = Field(None, description="The verdict's first reason, when it is not complete.")
    duration_s: float | None = Field(None, description="First to last recorded time over all devices.")
    cameras: list[str] = Field(default_factory=list)
    event_sensors: list[str] = Field(default_factory=list)
    size_bytes: int
    modified_utc: float = Field(description="File modification time, Unix seconds (the sort key).")
    error: str | None = None
    parts: list[str] = Field(
        default_factory=list, description="A multi-host take's part files (its manifest), by name."
    )
    parts_bytes: int = Field(0, description="The bytes of those parts found beside it (not in size_bytes).")
    part_of: str | None = Field(
        None, description="This file is a host's part <stem>.<host>.part.h5 no listed take claims: the stem."
    )
    part_host: str | None = Field(None, description="The host of that part.")


def take_files(directory: Path) -> list[Path]:
    """The take files directly in `directory`, oldest first (by modification time, then name)."""
    if not directory.is_dir():
        raise TakeError(f"{directory}: not a directory")
    try:
        files = [p for p in directory.iterdir() if p.suffix.lower() in TAKE_SUFFIXES and p.is_file()]
    except OSError as exc:
        raise TakeError(f"{directory}: cannot list it ({exc.strerror or exc})") from exc
    return sorted(files, key=lambda p: (p.stat().st_mtime, p.name))


def take_row(path: Path) -> TakeRow:
    """A take's row; a file that is not a readable take gets a row with `error`."""
    from rigd.take.reader import Take

    st = path.stat()
    base = {"path": str(path), "name": path.stem, "size_bytes": st.st_size, "modified_utc": st.st_mtime}
    try:
        with Take(path) as take:
            summary = take.summary()
            parts = [p.file for p in take.parts or [] if p.file]
    except TakeFormatError as exc:  # breaks the format's rules: damaged, never read further
        log.debug("takes: %s damaged: %s", path, exc)
        return TakeRow(**base, verdict="damaged", reason=str(exc), error=str(exc))
    except (OSError, RigdError) as exc:  # held by a live writer, not a take
        log.debug("takes: %s unreadable: %s", path, exc)
        return TakeRow(**base, error=str(exc))
    spans = [(c.t_first_us, c.t_last_us) for c in summary.cameras.values()]
    spans += [(e.t_first_us, e.t_last_us) for e in summary.event_sensors.values()]
    times = [t for span in spans for t in span if t is not None]
    duration = (max(times) - min(times)) / 1e6 if times else None
    reason = summary.verdict_reasons[0] if summary.verdict_reasons else summary.failure_reason
    return TakeRow(
        **base,
        status=summary.status,
        verdict=summary.verdict,
        reason=reason if summary.verdict != "complete" else None,
        duration_s=duration,
        cameras=list(summary.cameras),
        event_sensors=list(summary.event_sensors),
        parts=parts,
    )


def isolated_row(path: Path, timeout_s: float = READ_TIMEOUT_S) -> TakeRow:
    """`take_row` in a worker process (rigd.take.isolated): a take whose read hangs or crashes
    is a row with `error`, after `timeout_s` at most."""
    try:
        return run_isolated(take_row, path, timeout_s=timeout_s, what=str(path))
    except (OSError, RigdError) as exc:
        st = path.stat()
        return TakeRow(
            path=str(path), name=path.stem, size_bytes=st.st_size, modified_utc=st.st_mtime, error=str(exc)
        )


def list_takes(directory: Path, timeout_s: float = READ_TIMEOUT_S) -> list[TakeRow]:
    """Every take in `directory`, oldest first; each read in a worker with a deadline. The parts of
    a multi-host take are folded into its row."""
    rows = [isolated_row(p, timeout_s) for p in take_files(directory)]
    owner = {name: row for row in rows for name in row.parts}
    listed = []
    for row in rows:
        name = Path(row.path).name
        if name in owner and owner[name] is not row:
            owner[name].parts_bytes += row.size_bytes
            continue
        stem, _, host = name.removesuffix(".part.h5").rpartition(".")
        if re.fullmatch(PART_NAME, name) and stem:
            row.part_of, row.part_host = stem, host
        listed.append(row)
    return listed
