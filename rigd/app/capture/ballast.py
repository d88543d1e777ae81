"""Disk space held back while a take runs, so a full disk still lets the take be closed, and
how much a rig needs of it."""

from __future__ import annotations

import errno
import logging
import math
import os
import uuid
from collections.abc import Iterable
from pathlib import Path

from rigd.core.errors import ConfigError, TakeError
from rigd.core.settings import WriterConfig
from rigd.take.evt_sink import MAX_UNWRITTEN_BYTES, WORDS_CHUNK
from rigd.take.sinks import EVENT_WRITE_BLOCK
from rigd.take.take_state import WRITE_CHUNK_CACHE_BYTES

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


#: Bytes of one event as the take stores it uncompressed (x, y uint16; p uint8; t int64): what
#: a codec stores at worst.
_EVENT_BYTES = 13
#: The per-item series (trigger-in edges, frame times, pulses: int64 at most) are chunked and
#: buffered by this many rows (`rigd.take.sinks`); a failed take writes at most two partial
#: chunks of each.
_SERIES_ROWS = 4096
_SERIES_BYTES = 2 * _SERIES_ROWS * 8
#: HDF5 metadata a take writes when it is marked failed and closed (object headers, chunk
#: indexes, the superblock), its status attributes and the loss journal.
_METADATA_BYTES = 1 << 20


def minimum_ballast_bytes(writer: WriterConfig, frame_bytes: Iterable[int], n_event_sensors: int) -> int:
    """What marking a take failed and closing it on a full disk writes at most, once the
    ballast is given up: per event sensor its buffered events (a write block plus a chunk,
    uncompressed at worst) and what its four event columns hold in HDF5's chunk cache
    (`WRITE_CHUNK_CACHE_BYTES` each: none, the writer keeps no cache), or its EVT words not
    written yet (`MAX_UNWRITTEN_BYTES`) and its two tail slots, whichever is more, and its five
    trigger-in series; per camera its cached frames (none) and six frame series; the pulse
    series; the file's metadata and journal. With less, the take's `failed` mark and metadata
    may not reach the disk, and a take whose first flush never did cannot be read back (HDF5:
    "addr overflow"). `frame_bytes`: one frame of each camera."""
    columns = (EVENT_WRITE_BLOCK + writer.event_chunk) * _EVENT_BYTES + 4 * WRITE_CHUNK_CACHE_BYTES
    words = MAX_UNWRITTEN_BYTES + 2 * WORDS_CHUNK  # and its two tail slots
    per_sensor = max(columns, words) + 5 * _SERIES_BYTES
    cameras = sum(min(n, WRITE_CHUNK_CACHE_BYTES) + 6 * _SERIES_BYTES for n in frame_bytes)
    return n_event_sensors * per_sensor + cameras + 3 * _SERIES_BYTES + _METADATA_BYTES


def check_ballast(writer: WriterConfig, frame_bytes: Iterable[int], n_event_sensors: int) -> None:
    """Refuse a take whose `writer.disk_ballast_mb` is below `minimum_ballast_bytes` for this
    rig (ConfigError, one line naming the setting and the minimum)."""
    frames = list(frame_bytes)
    need_mb = math.ceil(minimum_ballast_bytes(writer, frames, n_event_sensors) / 1e6)
    if writer.disk_ballast_mb < need_mb:
        raise ConfigError(
            f"not starting a take: writer.disk_ballast_mb = {writer.disk_ballast_mb} is below the "
            f"{need_mb} MB this rig needs to close a take on a full disk ({n_event_sensors} event "
            f"sensor(s) at writer.event_chunk = {writer.event_chunk}, {len(frames)} camera(s)); "
            f"set it to at least {need_mb}"
        )
