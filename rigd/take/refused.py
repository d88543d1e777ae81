"""What the take writer does when the file system refuses its writes (disk full, a size limit).

HDF5 2.0 cannot be trusted with a file after a write it failed: a flush that fails half way
damages the header (it then refers past the file's end) and leaves HDF5 unable to close the
file ("slist already enabled"), its lock held until the process exits; and dirty data it cannot
write makes the close fail. So the writer checks for room before it flushes a failed take's
metadata, and closes a file it could not write through a sink that takes every write.
"""

from __future__ import annotations

import errno
import logging
import os
import resource
import shutil
from pathlib import Path

import h5py

log = logging.getLogger(__name__)

#: Free disk `fail` needs to flush the take's metadata (object headers, chunk indexes, the
#: status and the journal); with less it leaves the take as last flushed rather than risk a
#: flush that fails half way (the disk ballast frees far more: rigd.app.capture.ballast).
FAIL_FLUSH_ROOM_BYTES = 1 << 20


def no_room_to_flush(path: Path) -> OSError | None:
    """ENOSPC, saying how much is free, when the take's disk has less than FAIL_FLUSH_ROOM_BYTES."""
    free = shutil.disk_usage(path.parent).free
    if free >= FAIL_FLUSH_ROOM_BYTES:
        return None
    return OSError(
        errno.ENOSPC,
        f"{os.strerror(errno.ENOSPC)}: {free} bytes free on the take's disk, too few to "
        f"write its metadata ({FAIL_FLUSH_ROOM_BYTES} needed): the take stays as last flushed",
    )


def discard_pending_writes(f: h5py.File, path: Path) -> None:
    """Point the file's descriptor at a sink that takes every write (`_discard_sink`), so HDF5
    can close a file it failed to write: the close completes, the lock is released, and the
    file on disk stays exactly as the failure left it (recovery repairs and seals it). Closing
    with the dirty data HDF5 cannot write fails, and freeing the file's objects then crashes
    the process (HDF5 2.0). No fsync may run on the descriptor meanwhile."""
    fd = int(f.id.get_vfd_handle())
    sink = _discard_sink()
    try:
        os.dup2(sink, fd)
    finally:
        os.close(sink)
    log.error("take %s: writes HDF5 could not complete were discarded; the file stays as last flushed", path)


def _discard_sink() -> int:
    """A descriptor every write and extension succeeds on: an anonymous in-memory file, which
    HDF5 can extend to the end it records on close (it cannot extend /dev/null: EINVAL), or
    /dev/null under a file-size limit (which applies to the memory file too: EFBIG)."""
    if resource.getrlimit(resource.RLIMIT_FSIZE)[0] != resource.RLIM_INFINITY:
        return os.open(os.devnull, os.O_RDWR)
    return os.memfd_create("rigd-discarded-writes")
