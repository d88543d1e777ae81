"""Where an export is written: a staging directory beside `--out`, renamed into place when complete.

Why: an export killed (SIGKILL, power loss) or failed (disk full) must not leave a directory
that looks like an export. Everything is written under `.<name>.rigd-partial` in the parent of
`--out`; only when export.json is written is that directory renamed to `--out` (one rename, so
`--out` is either absent, the previous export, or the complete new one). The staging directory
is flock()ed while an export writes it, so a second run can tell a running export from one that
was killed, and say which.

Replacing a previous export (`--force`) takes two renames: the old one to `.<name>.rigd-old`,
then the new one into place, then the old one is removed; a kill between them leaves both
beside `--out`, and the next run names them.
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import re
import shutil
import time
from pathlib import Path
from typing import Any

from rigd.core.errors import ConfigError, RigdError

log = logging.getLogger(__name__)

#: What the staging directory holds besides the export: who writes it (removed after the rename).
MARKER = ".rigd-export-partial.json"

#: Top-level names an export writes (every format): a directory holding only these is an export.
_EXPORT_NAMES = re.compile(
    r"(images|ims|seg|events|segments|sparse|sparse_|calibration|cam\d+|export\.json|train_meta\.json"
    r"|test_meta\.json|init_pt_cld\.npz|transforms(_train|_val|_test)?\.json|sparse_pc\.ply|times\.json|split\.json"
    r"|points3D_multipleview\.bin|poses_bounds_multipleview\.npy)"
)


class ExportWriteError(RigdError):
    """Writing the export failed (disk full, I/O error); the partial output was removed."""


def partial_of(out: Path) -> Path:
    """The staging directory of `out`."""
    return out.parent / f".{out.name}.rigd-partial"


def old_of(out: Path) -> Path:
    """Where the previous export goes while `--force` swaps the new one in."""
    return out.parent / f".{out.name}.rigd-old"


def _describe_export(d: Path) -> str:
    """'nerfstudio of TAKE, written 2026-01-01 12:00 UTC' from a directory's export.json."""
    try:
        meta = json.loads((d / "export.json").read_text())
        when = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime((d / "export.json").stat().st_mtime))
        return f"{meta['format']} of {meta['take']}, written {when}"
    except (OSError, ValueError, KeyError, TypeError) as exc:
        return f"its export.json is unreadable: {exc}"


def _describe_partial(d: Path) -> str:
    try:
        meta = json.loads((d / MARKER).read_text())
        return f"{meta['format']} of {meta['take']} by pid {meta['pid']}, started {meta['started']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "no record of what it was writing"


def _is_locked(d: Path) -> bool:
    """True when a running export holds the staging directory's lock."""
    try:
        fd = os.open(d, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
    return False


def check_target(out: Path, force: bool) -> list[Path]:
    """Refuse an `--out` that cannot take the export, naming what is there and the way out.

    Returns the leftovers of earlier runs that `--force` allows to remove (`Staging` removes them)."""
    if not out.parent.exists():
        raise ConfigError(f"--out {out}: parent directory {out.parent} does not exist")
    if not out.parent.is_dir():
        raise ConfigError(f"--out {out}: parent {out.parent} is not a directory")
    if out.is_symlink():
        raise ConfigError(f"--out {out}: is a symbolic link; choose another --out")
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: is a file, not a directory; choose another --out")
    try:
        return _leftovers_of(out, force)
    except OSError as exc:
        raise ConfigError(f"--out {out}: cannot be read: {exc.strerror or exc}") from exc


def _leftovers_of(out: Path, force: bool) -> list[Path]:
    partial, old = partial_of(out), old_of(out)
    if partial.exists() and _is_locked(partial):
        raise ConfigError(
            f"--out {out}: another rigd export is writing it now ({_describe_partial(partial)}, "
            f"in {partial}); wait for it to finish"
        )
    left = []
    if partial.exists():
        left.append(
            f"an earlier export to it did not finish and left {partial} ({_describe_partial(partial)})"
        )
    if old.exists():
        left.append(f"an earlier --force replacement was interrupted and left the previous export in {old}")
    if left and not force:
        it = "them" if len(left) > 1 else "it"
        raise ConfigError(
            f"--out {out}: " + "; ".join(left) + f"; pass --force to remove {it} and export again"
        )
    leftovers = [p for p in (partial, old) if p.exists()]
    if out.is_dir():
        entries = sorted(p.name for p in out.iterdir())
        if not entries:
            return leftovers
        if (out / "export.json").is_file():
            if not force:
                raise ConfigError(
                    f"--out {out}: holds a complete export ({_describe_export(out)}); "
                    "pass --force to replace it"
                )
        elif all(_EXPORT_NAMES.fullmatch(n) for n in entries):
            if not force:
                raise ConfigError(
                    f"--out {out}: holds an incomplete export (no export.json: an earlier export did "
                    "not finish); pass --force to replace it"
                )
        else:
            shown = ", ".join(entries[:3]) + (", ..." if len(entries) > 3 else "")
            raise ConfigError(
                f"--out {out}: exists and holds files that are not an export ({shown}); "
                "--force replaces only an earlier export: choose another --out"
            )
    return leftovers


class Staging:
    """The staging directory of one export, locked while it is written."""

    def __init__(self, out: Path, leftovers: list[Path], info: dict[str, Any]) -> None:
        self.out = out
        self.dir = partial_of(out)
        for p in leftovers:
            log.warning("removing %s, left by an earlier export (--force)", p)
            shutil.rmtree(p)
        try:
            self.dir.mkdir()
        except OSError as exc:
            raise ConfigError(
                f"--out {out}: cannot create a directory in {out.parent}: {exc.strerror or exc}"
            ) from exc
        self._fd: int | None = os.open(self.dir, os.O_RDONLY | os.O_DIRECTORY)
        fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        started = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
        try:
            (self.dir / MARKER).write_text(json.dumps({**info, "pid": os.getpid(), "started": started}))
        except OSError as exc:
            self.discard()
            raise ExportWriteError(f"--out {out}: cannot write in {self.dir}: {exc.strerror or exc}") from exc

    def commit(self) -> None:
        """Move the complete export to `out` (replacing a previous export there)."""
        old = old_of(self.out)
        if self.out.is_dir() and any(self.out.iterdir()):
            os.rename(self.out, old)
        try:
            os.replace(self.dir, self.out)
        except OSError as exc:
            if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                raise
            raise ExportWriteError(
                f"--out {self.out}: it was filled while the export was written; the export is in {self.dir}"
            ) from exc
        (self.out / MARKER).unlink()
        self._unlock()
        if old.exists():
            shutil.rmtree(old)

    def discard(self) -> None:
        """Remove the staging directory (after a failure); raises when it cannot be removed."""
        self._unlock()
        shutil.rmtree(self.dir)

    def _unlock(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
