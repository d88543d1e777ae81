"""Opening take files and the small HDF5 helpers every take module shares.

Opening goes through `open_h5` so a take a live writer holds (HDF5 file lock) is never opened
twice, and a take a failed write left short is reported as such (`TakeTruncatedError`) rather
than as a corrupt file; `open_extended` and `ZeroPadded` are the two ways recovery gets at
such a take (writable, or read-only without changing a byte).
"""

from __future__ import annotations

import datetime as _dt
import errno
import io
import logging
import os
import re
import threading
from pathlib import Path
from typing import Any

import h5py
import hdf5plugin
import numpy as np
from numpy.typing import NDArray

from rigd.core.errors import TakeError, TakeFormatError, TakeInUseError, TakeTruncatedError
from rigd.core.layout import Root
from rigd.core.schema import SCHEMA_NAME, SCHEMA_VERSION
from rigd.take.structure import check_regular_file, check_structure

log = logging.getLogger(__name__)

#: Root attr: the real end of a truncated take that resume extended with a hole; chunks past it
#: were never written. Removed once check_repair has trimmed them away.
TRUNCATED_EOF_ATTR = Root.TRUNCATED_EOF
_TRUNCATED_RE = re.compile(r"truncated file: eof = (\d+),.*stored_eof = (\d+)")
_ADDR_OVERFLOW_RE = re.compile(r"addr overflow, addr = (\d+), size = (\d+), eoa = (\d+)")


def describe_open_error(path: Path, exc: BaseException) -> str:
    """One line for a file HDF5 cannot open, saying what is wrong where HDF5's message is
    cryptic: its header records an end before data it points to (a write failed before the
    first flush reached the disk: disk full?)."""
    m = _ADDR_OVERFLOW_RE.search(str(exc))
    if m:
        addr, size, eoa = (int(v) for v in m.groups())
        return (
            f"{path}: damaged by a failed write (disk full before the first flush?): its header "
            f"records the file ending at byte {eoa}, yet refers to {size} bytes at byte {addr}; "
            "HDF5 refuses it and `rigd recover` cannot repair it"
        )
    return f"{path}: cannot be opened as an HDF5 file: {exc}"


_ERRNO_RE = re.compile(r"errno = (\d+)")
#: gzip level: 1 keeps write speed usable; with the shuffle filter it loses little ratio.
_GZIP_LEVEL = 1


def utc_now(timespec: str = "seconds") -> str:
    """ISO 8601 UTC timestamp, the form every take attr ending in `_utc` holds."""
    return _dt.datetime.now(_dt.UTC).isoformat(timespec=timespec)


def attr_text(value: Any) -> str:
    """A string attr or scalar as str: h5py hands back bytes for fixed-length strings."""
    return value.decode("utf-8") if isinstance(value, bytes) else str(value)


def as_oserror(exc: BaseException) -> OSError:
    """HDF5 reports some failed writes (a flush, a close) as RuntimeError; callers handle a
    file system that refuses writes as OSError, with the errno HDF5 saw (ENOSPC: disk full)."""
    if isinstance(exc, OSError):
        return exc
    m = _ERRNO_RE.search(str(exc))
    return OSError(int(m.group(1)) if m else errno.EIO, str(exc))


def compression_options(codec: str, *, shuffle: bool) -> dict[str, Any]:
    """h5py dataset keywords for a WriterConfig codec name.

    The byte-shuffle filter groups the constant high bytes of int64 times and uint16
    coordinates, which is what makes the fast codecs effective on event streams.
    """
    opts: dict[str, Any]
    if codec == "none":
        return {}
    if codec == "lz4":
        opts = dict(hdf5plugin.LZ4())
    elif codec == "zstd":
        opts = dict(hdf5plugin.Zstd(clevel=3))
    elif codec == "gzip":
        opts = {"compression": "gzip", "compression_opts": _GZIP_LEVEL}
    else:
        raise TakeError(f"unknown compression {codec!r} (use none, lz4, zstd or gzip)")
    if shuffle:
        opts["shuffle"] = True
    return opts


def append_rows(ds: h5py.Dataset, start: int, data: NDArray[Any]) -> None:
    """Store `data` at rows [start, start + len), growing the dataset when it is too short."""
    end = start + data.shape[0]
    if ds.shape[0] < end:
        ds.resize((end, *ds.shape[1:]))
    ds[start:end] = data


def write_chunk(ds: h5py.Dataset, coord: tuple[int, ...], data: Any, filter_mask: int = 0) -> None:
    """`write_direct_chunk` that a failed write leaves retryable.

    HDF5 (1.14) notes where a new chunk goes before writing its bytes and indexes the chunk only
    once the write succeeded. A write that fails (disk full) leaves that note behind, and the
    retry of the same chunk at the same size then writes the bytes but never indexes them: the
    chunk reads back as fill value. Looking up another chunk replaces the note, so the retry
    allocates and indexes afresh; a retry HDF5 still did not index is an error, never a gap.
    """
    try:
        ds.id.write_direct_chunk(coord, data, filter_mask)
    except Exception:
        _forget_last_chunk(ds, coord)
        raise


def chunk_is_stored(ds: h5py.Dataset, coord: tuple[int, ...]) -> bool:
    """Whether the dataset's chunk index holds the chunk at `coord` (not a fill-value gap)."""
    return ds.id.get_chunk_info_by_coord(coord).byte_offset is not None


def _forget_last_chunk(ds: h5py.Dataset, coord: tuple[int, ...]) -> None:
    shape = ds.shape
    step = ds.chunks[0] if ds.chunks else 1
    other = coord[0] - step if coord[0] >= step else coord[0] + step
    try:
        if other >= shape[0]:  # a dataset of one chunk: look one chunk past its end
            ds.resize((other + 1, *shape[1:]))
        ds[(other, *(0 for _ in shape[1:]))]  # one element: a lookup of that chunk
        if ds.shape != shape:
            ds.resize(shape)
    except Exception as exc:  # noqa: BLE001 - the failed write is what the caller raises
        log.warning("%s: chunk %s: could not clear HDF5's note of the failed write: %s", ds.name, coord, exc)


def fsync_dir(directory: Path) -> None:
    """Make a new file's name durable (POSIX: fsync the directory that holds it)."""
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def is_lock_error(exc: OSError) -> bool:
    """Whether h5py refused to open a file because another process holds its HDF5 lock."""
    return isinstance(exc, BlockingIOError) or "errno = 11," in str(exc)


def open_h5(path: Path, mode: str, *, rdcc_nbytes: int | None = None) -> h5py.File:
    """Open with HDF5 file locking on, so a take a live writer holds is never opened
    (best-effort: file systems without locks open anyway). `rdcc_nbytes`: each dataset's raw
    chunk cache (None: HDF5's default)."""
    if not path.exists():
        raise TakeError(f"{path}: no such take file")
    check_regular_file(path)
    try:
        return checked(path, h5py.File(path, mode, locking="best-effort", rdcc_nbytes=rdcc_nbytes))
    except OSError as exc:
        if is_lock_error(exc):
            raise TakeInUseError(
                f"{path}: in use: another process has it open for writing (HDF5 file lock)"
            ) from exc
        m = _TRUNCATED_RE.search(str(exc))
        if m:
            eof, stored = int(m.group(1)), int(m.group(2))
            raise TakeTruncatedError(
                f"{path}: truncated by a failed write (disk full?): the file ends at byte {eof}, its "
                f"header records {stored}; `rigd recover` extends it and trims what was never written",
                eof,
                stored,
            ) from exc
        raise TakeFormatError(describe_open_error(path, exc)) from exc


def checked(path: Path, f: h5py.File, size: int | None = None, *, part: bool = False) -> h5py.File:
    """`f` once its structure passed `check_structure` (rigd/take/structure.py); closed and a
    TakeFormatError otherwise, before anything read a dataset of it. `size`, `part`: see there."""
    try:
        check_structure(f, path, size, part=part)
    except BaseException:
        f.close()
        raise
    return f


def open_checked(path: Path, mode: str = "r", *, part: bool = False, **kwargs: Any) -> h5py.File:
    """`h5py.File(path, mode)` for a take a reader is about to trust: a regular file whose
    structure passed `check_structure` (`part`: as a multi-host take's part file); any failure
    to open it is one TakeFormatError."""
    check_regular_file(path)
    try:
        f = h5py.File(path, mode, **kwargs)
    except (OSError, ValueError) as exc:
        if isinstance(exc, OSError) and is_lock_error(exc):
            raise TakeInUseError(
                f"{path}: in use: another process has it open for writing (HDF5 file lock)"
            ) from exc
        raise TakeFormatError(describe_open_error(path, exc)) from exc
    return checked(path, f, part=part)


def open_extended(path: Path, exc: TakeTruncatedError) -> h5py.File:
    """Open a truncated take for writing, first given the length its superblock records (a
    sparse hole, no disk space needed) and noting the real end, so check_repair treats what
    lay past it as never written."""
    size = path.stat().st_size
    if size != exc.eof or exc.stored_eof <= exc.eof:
        raise TakeFormatError(f"{path}: changed while being recovered (size {size}, expected {exc.eof})")
    log.warning(
        "take %s is %d bytes short of what its header records (a write failed); extending it with a hole",
        path,
        exc.stored_eof - exc.eof,
    )
    os.truncate(path, exc.stored_eof)
    f = open_h5(path, "r+")
    f.attrs[TRUNCATED_EOF_ATTR] = np.int64(exc.eof)
    f.flush()
    return f


class ZeroPadded(io.RawIOBase):
    """Read-only view of a truncated file, zeros past its end up to `size`: lets h5py open a
    take a failed write left short without changing a byte of it (dry runs)."""

    def __init__(self, path: Path, size: int) -> None:
        super().__init__()
        self._f = path.open("rb")
        self._real = os.fstat(self._f.fileno()).st_size
        self._size = size
        self._pos = 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self._pos, io.SEEK_END: self._size}[whence]
        self._pos = base + offset
        return self._pos

    def tell(self) -> int:
        return self._pos

    def readinto(self, buf: Any) -> int:
        view = memoryview(buf).cast("B")
        n = max(0, min(len(view), self._size - self._pos))
        got = 0
        if self._pos < self._real:
            self._f.seek(self._pos)
            got = self._f.readinto(view[: min(n, self._real - self._pos)]) or 0
        view[got:n] = bytes(n - got)
        self._pos += n
        return n

    def close(self) -> None:
        self._f.close()
        super().close()


def check_header(f: h5py.File, path: Path) -> str:
    """Schema name and major version of an open take; returns its schema_version."""
    schema = attr_text(f.attrs.get(Root.SCHEMA, ""))
    if schema != SCHEMA_NAME:
        raise TakeFormatError(f"{path}: /: attr schema is {schema!r}, expected {SCHEMA_NAME!r}")
    version = attr_text(f.attrs.get(Root.SCHEMA_VERSION, ""))
    if version.split(".")[0] != SCHEMA_VERSION.split(".")[0]:
        raise TakeFormatError(
            f"{path}: /: schema_version {version!r} is not readable by this rigd "
            f"(reads {SCHEMA_VERSION.split('.')[0]}.x)"
        )
    return version


def require_group(parent: h5py.Group, name: str, where: str) -> h5py.Group:
    """`parent[name]` as a group, or a TakeFormatError naming the file (`where`) and path."""
    node = parent.get(name)
    if not isinstance(node, h5py.Group):
        raise TakeFormatError(f"{where}: {parent.name.rstrip('/')}/{name} is missing or not a group")
    return node


def require_dataset(parent: h5py.Group, name: str, where: str) -> h5py.Dataset:
    """`parent[name]` as a dataset, or a TakeFormatError naming the file (`where`) and path."""
    node = parent.get(name)
    if not isinstance(node, h5py.Dataset):
        raise TakeFormatError(f"{where}: {parent.name.rstrip('/')}/{name} is missing or not a dataset")
    return node


class Syncer:
    """The take's fsync beside its writer: a flush hands the fsync over and the writer goes on
    writing; the next flush (or the close) waits for it first, so at most one is outstanding and
    what a flush wrote is on the disk by the end of the next one. A failed fsync's error comes
    out of that wait. (An fsync of a second's data takes the writer thread ~0.3-0.6 s at the
    disk's speed; in line, the writer falls that far behind every second.)"""

    def __init__(self, label: str) -> None:
        self._label = label
        self._thread: threading.Thread | None = None
        self._error: OSError | None = None

    def start(self, fd: int) -> None:
        self.wait()
        thread = threading.Thread(target=self._run, args=(fd,), name=f"fsync {self._label}", daemon=True)
        self._thread = thread
        thread.start()

    def _run(self, fd: int) -> None:
        try:
            os.fsync(fd)
        except OSError as exc:
            self._error = exc

    def wait(self) -> None:
        """Until the outstanding fsync is done; raises what it failed with."""
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join()
        error, self._error = self._error, None
        if error is not None:
            raise error
