"""Serving the daemon's own take files over its control socket: what `rigd takes gather` copies
a multi-host take's parts with (`take_read`, `take_stat`; docs/take-format.md "Multi-host takes").

The control socket is as private as the daemon (a 0700 runtime directory, or CurveZMQ beyond
loopback), so these commands add no reader the socket did not already trust; still, they serve
only a plain file name in the daemon's take directory (no path, no hidden file, no symbolic
link, a regular file), and never more than `MAX_READ_BYTES` a request. The checksum of a
multi-gigabyte part takes seconds to compute: it runs in a thread of its own, and `take_stat`
answers at once with `sha256: null, hashing: true` until it is known, so the control loop never
waits for a disk.
"""

from __future__ import annotations

import base64
import hashlib
import logging
import os
import re
import stat
import threading
from pathlib import Path
from typing import Any

from rigd.app.service.protocol import PAYLOAD_KEY, TAKE_READ_MAX_BYTES
from rigd.app.service.requests import RequestError

log = logging.getLogger(__name__)

#: Largest `take_read` length (the reply carries it base64-encoded: 4/3 of it).
MAX_READ_BYTES = TAKE_READ_MAX_BYTES
#: A take file's name: no directory, not hidden.
TAKE_NAME = r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,250}\.h5$"
_HASH_BLOCK = 4 << 20
#: Checksums kept (by file identity and version); older ones are forgotten.
_KEEP = 64


def take_file(take_dir: Path, name: str) -> Path:
    """`take_dir / name` for a plain take file name; a RequestError naming `args.file` else."""
    if not re.fullmatch(TAKE_NAME, name) or ".." in name:
        raise RequestError(
            "bad_request", f"{name!r} is not a take file name in the daemon's take directory", "args.file"
        )
    return take_dir / name


def _open(path: Path) -> tuple[int, os.stat_result]:
    """A descriptor of the regular file at `path` (never through a symbolic link, never
    blocking on a FIFO) and its stat."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise RequestError("take_error", f"no take file {path.name} in the daemon's take directory") from None
    except OSError as exc:
        raise RequestError("take_error", f"{path.name}: cannot be read: {exc.strerror}") from None
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):
        os.close(fd)
        raise RequestError("take_error", f"{path.name}: is not a regular file")
    return fd, st


def read_take(take_dir: Path, name: str, offset: int, length: int, binary: bool = False) -> dict[str, Any]:
    """`length` bytes of the take file from `offset` (fewer at its end) and its size now; with
    `binary` the bytes go in the reply's second frame (PAYLOAD_KEY), else base64 in the JSON."""
    if length > MAX_READ_BYTES:
        raise RequestError("bad_request", f"length {length} is over {MAX_READ_BYTES}", "args.length")
    fd, st = _open(take_file(take_dir, name))
    try:
        data = os.pread(fd, length, offset) if offset < st.st_size else b""
    finally:
        os.close(fd)
    out: dict[str, Any] = {"file": name, "offset": offset, "size": st.st_size}
    if binary:
        out["length"] = len(data)
        out[PAYLOAD_KEY] = data
    else:
        out["data_b64"] = base64.b64encode(data).decode("ascii")
    return out


class TakeHashes:
    """sha256 of take files, computed in the background, keyed by what identifies one version
    of a file (device, inode, size, modification time)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._done: dict[tuple[int, int, int, int], str] = {}
        self._running: dict[tuple[int, int, int, int], threading.Thread] = {}
        self._errors: dict[tuple[int, int, int, int], str] = {}

    def stat(self, take_dir: Path, name: str) -> dict[str, Any]:
        """Size, modification time and, once computed, the sha256 of the take file."""
        path = take_file(take_dir, name)
        fd, st = _open(path)
        os.close(fd)
        key = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
        with self._lock:
            sha = self._done.get(key)
            error = self._errors.pop(key, None)
            if sha is None and error is None and key not in self._running:
                th = threading.Thread(target=self._hash, args=(path, key), name=f"sha256 {name}", daemon=True)
                self._running[key] = th
                th.start()
        if error is not None:
            raise RequestError("take_error", f"{name}: its checksum could not be computed: {error}")
        return {
            "file": name,
            "size": st.st_size,
            "mtime_ns": st.st_mtime_ns,
            "sha256": sha,
            "hashing": sha is None,
        }

    def _hash(self, path: Path, key: tuple[int, int, int, int]) -> None:
        h = hashlib.sha256()
        error: str | None = None
        try:
            fd, st = _open(path)
            with os.fdopen(fd, "rb") as f:
                if (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns) != key:
                    error = "the file changed while its checksum was asked for; ask again"
                else:
                    while block := f.read(_HASH_BLOCK):
                        h.update(block)
        except (OSError, RequestError) as exc:
            error = str(exc)
        with self._lock:
            self._running.pop(key, None)
            if error is not None:
                log.warning("take %s: sha256 failed: %s", path, error)
                self._errors[key] = error
                return
            self._done[key] = h.hexdigest()
            while len(self._done) > _KEEP:
                self._done.pop(next(iter(self._done)))
