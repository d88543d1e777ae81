"""Disk space held back while a take runs, so a full disk still lets the take be closed."""

from __future__ import annotations

import errno
import logging
import os
import uuid
from pathlib import Path

from rigd.core.errors import TakeError

log = logging.getLogger(__name__)


class Ballast:
    """Disk space held back while a take runs and given up the moment the disk is full, so
    the take can still be closed cleanly (an HDF5 file that cannot write its metadata on
    close is left inconsistent in memory). The file name carries the owner's PID, so the
    ballast of a killed process is told from a live one's and removed by
    `remove_stale_ballast` (at every take's start, the daemon's start and `rigd recover`)."""

    PREFIX = ".rigd-ballast-"

    def __init__(self, directory: Path, size_bytes: int) -> None:
        self.path = directory / f"{self.PREFIX}{os.getpid()}-{uuid.uuid4().hex[:8]}"
        self.size = size_bytes
        if size_bytes <= 0:
            return
        fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
        try:
            try:
                os.posix_fallocate(fd, 0, size_bytes)
            except OSError as exc:
                if exc.errno != errno.EOPNOTSUPP:
                    raise
                block = b"\0" * (1 << 20)  # file systems without fallocate: write it out
                for _ in range(0, size_bytes, len(block)):
                    os.write(fd, block)
        except OSError as exc:
            os.close(fd)
            self.path.unlink(missing_ok=True)
            raise TakeError(
                f"cannot hold {size_bytes / 1e6:.0f} MB of ballast in {directory}: {exc.strerror} "
                "(writer.disk_ballast_mb)"
            ) from exc
        os.close(fd)

    def release(self, *, emergency: bool = False) -> None:
        """Give the space back; `emergency`: the disk is full (said as a warning)."""
        if self.size > 0 and self.path.exists():
            self.path.unlink()
            level = logging.WARNING if emergency else logging.DEBUG
            log.log(level, "released %.0f MB of disk ballast (%s)", self.size / 1e6, self.path)


def _owner_alive(path: Path) -> bool:
    """Whether the process that made this ballast file still runs (names without a PID are
    from before PIDs were written, so their owner is gone)."""
    pid_text = path.name.removeprefix(Ballast.PREFIX).partition("-")[0]
    if not pid_text.isdigit():
        return False
    pid = int(pid_text)
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's live process
    return True


def remove_stale_ballast(directory: Path) -> int:
    """Remove the ballast files of processes that are gone; returns how many."""
    n = 0
    for p in directory.glob(f"{Ballast.PREFIX}*"):
        if _owner_alive(p):
            continue
        p.unlink(missing_ok=True)
        log.info("removed stale disk ballast %s (its capture was killed)", p)
        n += 1
    return n
