"""Files an export writes, made so that a full disk is one OSError naming the file: HDF5 outputs
that HDF5 never sees fail (`h5_output`), images written by Python rather than cv2 (`write_image`).
"""

from __future__ import annotations

import io
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import h5py
import numpy as np
from numpy.typing import NDArray

from rigd.core.errors import TakeError

if TYPE_CHECKING:
    from _typeshed import ReadableBuffer, WriteableBuffer

U8 = NDArray[np.uint8]


class _OutputFile(io.RawIOBase):
    """The file under an HDF5 output (h5py's fileobj driver), which HDF5 never sees fail.

    Why: when a write fails (disk full), HDF5 marks the file broken; h5py's close raises and
    leaves the file and a dataset open, and HDF5 touches them again when they are collected or
    at exit, and crashes (SIGSEGV). Here the first failed write is kept in `error` and it and
    every later write go to memory (read back from there), so HDF5 stays consistent and closes;
    `H5Output.check` and the end of `h5_output` raise the error, and the caller removes the file.
    """

    def __init__(self, path: Path) -> None:
        super().__init__()
        self._fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o644)
        self._pos = 0
        self.error: OSError | None = None
        self._kept: list[tuple[int, bytes]] = []  # (offset, data) written after the failure

    def readable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def _size(self) -> int:
        return max([os.fstat(self._fd).st_size, *(off + len(b) for off, b in self._kept)])

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        base = {os.SEEK_SET: 0, os.SEEK_CUR: self._pos, os.SEEK_END: self._size()}[whence]
        self._pos = base + offset
        return self._pos

    def tell(self) -> int:
        return self._pos

    def readinto(self, buffer: WriteableBuffer) -> int:
        view = memoryview(buffer).cast("B")
        n = max(min(view.nbytes, self._size() - self._pos), 0)
        got = os.pread(self._fd, n, self._pos)
        view[: len(got)] = got
        view[len(got) : n] = bytes(n - len(got))
        for off, data in self._kept:  # later writes win
            lo, hi = max(off, self._pos), min(off + len(data), self._pos + n)
            if lo < hi:
                view[lo - self._pos : hi - self._pos] = data[lo - off : hi - off]
        self._pos += n
        return n

    def write(self, data: ReadableBuffer) -> int:
        view = memoryview(data).cast("B")
        if self.error is None:
            done = 0
            try:
                while done < view.nbytes:  # a write may be short
                    done += os.pwrite(self._fd, view[done:], self._pos + done)
            except OSError as exc:
                self.error = exc
        if self.error is not None:
            self._kept.append((self._pos, bytes(view)))
        self._pos += view.nbytes
        return view.nbytes

    def truncate(self, size: int | None = None) -> int:
        """Set the file's end (HDF5 does at close: its end of allocated space, often past the last
        write); after a failure only the written part is on disk, and the file is removed."""
        size = self._pos if size is None else size
        if self.error is None:
            try:
                os.ftruncate(self._fd, size)
            except OSError as exc:
                self.error = exc
        return size

    def flush(self) -> None:
        return None

    def close(self) -> None:
        if not self.closed:
            os.close(self._fd)
        super().close()


@dataclass
class H5Output:
    """An HDF5 file being written (`h5_output`)."""

    file: h5py.File
    path: Path
    _raw: _OutputFile

    def check(self) -> None:
        """Raise the first failed write (an OSError naming the file); call between large writes
        so that a full disk stops the writer instead of filling memory."""
        if self._raw.error is not None:
            e = self._raw.error
            raise OSError(e.errno, e.strerror or str(e), str(self.path)) from e


@contextmanager
def h5_output(path: Path) -> Iterator[H5Output]:
    """A new HDF5 file to write that closes cleanly when the disk fills; a failed write raises
    (an OSError naming the file) at `check` or when the block ends."""
    raw = _OutputFile(path)
    try:
        with h5py.File(raw, "w") as f:
            out = H5Output(f, path, raw)
            yield out
    finally:
        raw.close()
    out.check()


def write_image(dest: Path, img: U8, params: Sequence[int] = ()) -> None:
    """Encode with cv2 and write with Python: a full disk is an OSError naming the file, where
    cv2.imwrite would only return False."""
    ok, buf = cv2.imencode(dest.suffix, img, list(params))
    if not ok:
        raise TakeError(f"could not encode {dest.name} ({img.shape[1]}x{img.shape[0]})")
    try:
        dest.write_bytes(buf.tobytes())
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror, str(dest)) from exc
