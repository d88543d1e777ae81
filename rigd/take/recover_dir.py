"""Recovering every unfinished take in a directory, one take at a time.

One file that cannot be read (zero bytes, random bytes, not HDF5, truncated past its
attributes, a corrupt chunk) must not stop the others from being sealed, nor the daemon
from starting: each such file becomes a `RecoveryProblem` (a log line, an entry in the
report) and the loop goes on. The daemon moves unreadable files aside to
`<take_dir>/unreadable/` so that the next start does not trip over them again; the files
are kept, never deleted.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field

from rigd.core.errors import NotATakeError, TakeError
from rigd.take.isolated import READ_TIMEOUT_S, recovery_timeout_s, run_isolated
from rigd.take.recover import RecoveryReport, needs_recovery, recover_take

log = logging.getLogger(__name__)

#: What reading a damaged file can raise besides TakeError: h5py reports HDF5 library
#: failures (bad superblock, heap or chunk) as OSError, malformed attributes and datatypes
#: as ValueError / TypeError, missing objects as KeyError; a worker (rigd.take.isolated) reports
#: any other error it met as RuntimeError.
READ_ERRORS: tuple[type[Exception], ...] = (TakeError, OSError, ValueError, KeyError, TypeError, RuntimeError)

#: Where the daemon moves files it cannot read, under its take directory.
UNREADABLE_DIR = "unreadable"

_TAKE_SUFFIXES = (".h5", ".hdf5")


class RecoveryProblem(BaseModel):
    """A file recovery could not handle: which, and why (in the reports next to the
    `RecoveryReport`s of the takes it did handle)."""

    model_config = ConfigDict(extra="forbid")

    path: str
    error: str = Field(description="Why the file could not be read or sealed.")
    moved_to: str | None = Field(None, description="Where it was moved aside to, if it was.")

    def line(self) -> str:
        """One line for people: the file and why."""
        moved = f" (moved to {self.moved_to})" if self.moved_to else ""
        return f"{self.path}: {self.error}{moved}"


@dataclass(slots=True)
class DirScan:
    """What `scan_dir` found: takes to recover and files that could not be read."""

    unfinished: list[Path] = field(default_factory=list)
    unreadable: list[RecoveryProblem] = field(default_factory=list)


def _why(exc: Exception, path: Path) -> str:
    """The reason to report, without the file name (the report line starts with it): our
    errors say what is wrong; library errors get their type."""
    if not isinstance(exc, TakeError):
        return f"{type(exc).__name__}: {exc}"
    return str(exc).removeprefix(f"{path}: ")


def _candidates(d: Path) -> Iterator[Path]:
    for p in sorted(d.iterdir()):
        if p.suffix.lower() in _TAKE_SUFFIXES and p.is_file():
            yield p


def _needs_here(p: Path) -> bool | None:
    try:
        return needs_recovery(p)
    except NotATakeError:
        return None


def _needs(p: Path) -> bool | None:
    """True: unfinished (or held by a live writer); False: nothing to do; None: not a rigd
    take. Raises one of READ_ERRORS for a file that cannot be read, or whose read hangs or
    crashes its worker (rigd.take.isolated)."""
    return run_isolated(_needs_here, p, timeout_s=READ_TIMEOUT_S, what=str(p))


def scan_dir(directory: str | Path) -> DirScan:
    """Takes (`*.h5`, `*.hdf5`) in `directory` that need `recover_take`, sorted by name, and
    the files that could not be read; HDF5 files that are not rigd takes are skipped with a
    log line. Raises TakeError only when the directory itself cannot be listed."""
    d = Path(directory)
    if not d.is_dir():
        raise TakeError(f"{d}: not a directory")
    out = DirScan()
    try:
        files = list(_candidates(d))
    except OSError as exc:
        raise TakeError(f"{d}: cannot be listed: {exc.strerror or exc}") from exc
    for p in files:
        try:
            needs = _needs(p)
        except READ_ERRORS as exc:
            # Returned, and reported once by the caller (`log_problems`, or the command's lines).
            log.info("%s cannot be read as a take: %s", p, _why(exc, p))
            out.unreadable.append(RecoveryProblem(path=str(p), error=f"unreadable: {_why(exc, p)}"))
            continue
        if needs is None:
            log.info("skipping %s: not a rigd take", p)
        elif needs:
            out.unfinished.append(p)
    return out


def move_aside(path: Path, take_dir: Path) -> Path:
    """Move `path` into `<take_dir>/unreadable/`, keeping its name; on a clash the name gets
    `.1`, `.2`, ... before the suffix. Never overwrites, never deletes. Raises OSError."""
    dest_dir = take_dir / UNREADABLE_DIR
    dest_dir.mkdir(exist_ok=True)
    dest = dest_dir / path.name
    n = 0
    while True:
        try:
            # A hard link fails on an existing name instead of replacing it (rename would).
            os.link(path, dest)
        except FileExistsError:
            n += 1
            dest = dest_dir / f"{path.stem}.{n}{path.suffix}"
            continue
        except OSError as exc:  # no hard links on this file system: rename to a free name
            log.info("no hard link for %s (%s); renaming", path, exc.strerror or exc)
            while dest.exists():
                n += 1
                dest = dest_dir / f"{path.stem}.{n}{path.suffix}"
            path.rename(dest)
            return dest
        path.unlink()
        return dest


def _recover_here(path: Path, dry_run: bool) -> RecoveryReport:
    return recover_take(path, dry_run=dry_run)


def recover_one(path: Path, *, dry_run: bool = False) -> RecoveryReport | RecoveryProblem:
    """`recover_take` in a worker process with a deadline (rigd.take.isolated), with a file it
    cannot read or seal, or whose recovery hangs or crashes, reported instead of raised."""
    try:
        timeout = recovery_timeout_s(path.stat().st_size)
        return run_isolated(_recover_here, path, dry_run, timeout_s=timeout, what=str(path))
    except READ_ERRORS as exc:
        log.info("recovering %s failed: %s", path, _why(exc, path))  # the caller reports it
        return RecoveryProblem(path=str(path), error=_why(exc, path))


def log_problems(results: list[RecoveryReport | RecoveryProblem]) -> None:
    """Log each problem once, for a caller with no reader of its own (the daemon)."""
    for r in results:
        if isinstance(r, RecoveryProblem):
            log.error("%s", r.line())


def _move_problem(problem: RecoveryProblem, directory: Path) -> None:
    """Move the file of `problem` aside, noting where, or noting why it could not be."""
    try:
        problem.moved_to = str(move_aside(Path(problem.path), directory))
    except OSError as exc:
        log.error("could not move %s aside: %s", problem.path, exc)
        problem.error += f"; could not move it aside: {exc}"
    else:
        log.warning("moved unreadable %s to %s", problem.path, problem.moved_to)


def recover_dir(
    directory: str | Path,
    *,
    dry_run: bool = False,
    move_unreadable: bool = False,
    before_each: Callable[[Path], None] | None = None,
) -> list[RecoveryReport | RecoveryProblem]:
    """Recover every unfinished take in `directory`; files it cannot read or seal are
    reported (and, with `move_unreadable`, moved aside to `<directory>/unreadable/` so that
    the next run does not trip over them again), never fatal.

    `before_each` is called with each take before it is recovered (the daemon tells systemd
    which take it is sealing, since that can take minutes). Raises TakeError only when the
    directory itself cannot be listed."""
    d = Path(directory)
    scan = scan_dir(d)
    move = move_unreadable and not dry_run
    out: list[RecoveryReport | RecoveryProblem] = []
    for problem in scan.unreadable:
        if move:
            _move_problem(problem, d)
        out.append(problem)
    for path in scan.unfinished:
        if before_each is not None:
            before_each(path)
        result = recover_one(path, dry_run=dry_run)
        if move and isinstance(result, RecoveryProblem):
            _move_problem(result, d)
        out.append(result)
    return out


def find_unfinished(directory: str | Path) -> list[Path]:
    """Takes (`*.h5`, `*.hdf5`) in `directory` that need `recover_take`, sorted by name (a take
    a live process holds included); files that cannot be read are logged and left out."""
    return scan_dir(directory).unfinished
