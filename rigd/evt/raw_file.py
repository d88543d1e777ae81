"""RAW files: `RawReader` (a file as decoded chunks in constant memory), `read_raw` (a whole
file), writing and one-shot encoding, and the decoder warm-up a capture runs before its take.
All decoding goes through `raw.StreamDecoder`."""

from __future__ import annotations

import mmap
import os
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType
from typing import BinaryIO

import numpy as np

from rigd.core.errors import EventDataError
from rigd.core.events import EventArray, TriggerEvents
from rigd.evt import evt2, evt3, evt21
from rigd.evt.errors import EvtDecodeError
from rigd.evt.kernels import JUMP_CONFIRM
from rigd.evt.raw import Decoded, StreamDecoder, join_decoded
from rigd.evt.raw_header import RawHeader, parse_raw_header


class RawReader:
    """Iterate a RAW file as decoded chunks of `chunk_bytes` input bytes, in constant memory.

    A file without any `%` header line is refused unless `fmt` is given: random bytes or another
    file type would otherwise decode as EVT 3.0 into noise. Header problems (a geometry the
    decoder cannot take) are EventDataErrors naming the file.
    """

    def __init__(
        self,
        path: str | Path,
        chunk_bytes: int = 1 << 20,
        *,
        strict: bool = False,
        fmt: str | None = None,
        width: int | None = None,
        height: int | None = None,
        jump_confirm: int = JUMP_CONFIRM,
    ) -> None:
        self.path = Path(path)
        self._f: BinaryIO = self.path.open("rb")
        try:
            self.header = parse_raw_header(self._f)
            if fmt is not None:
                self.header.fmt = fmt
            elif not self.header.fields:
                raise EventDataError(
                    f"{self.path}: no RAW header ('% evt' / '% format' lines); not a Prophesee RAW file"
                )
            self.decoder = StreamDecoder(
                self.header.fmt,
                width=width or self.header.width,
                height=height or self.header.height,
                strict=strict,
                offset=self.header.size,
                jump_confirm=jump_confirm,
            )
        except EvtDecodeError:
            self._f.close()
            raise
        except EventDataError as exc:
            self._f.close()
            msg = str(exc)
            raise EventDataError(msg if msg.startswith(str(self.path)) else f"{self.path}: {msg}") from None
        except OSError:
            self._f.close()
            raise
        self.chunk_bytes = max(1, int(chunk_bytes))

    def __iter__(self) -> Iterator[Decoded]:
        try:
            yield from self._mapped()
            while True:  # what the map does not cover: a file that grew, or one that maps not
                chunk = self._f.read(self.chunk_bytes)
                if not chunk:
                    break
                yield self.decoder.feed(chunk)
            tail = self.decoder.finish()  # words held at a time jump still undecided
            if len(tail.events) or len(tail.triggers):
                yield tail
            self.decoder.log_stats()
        finally:
            self.close()

    def _mapped(self) -> Iterator[Decoded]:
        """The file's chunks decoded in place from a read-only map of the page cache: no copy of
        each chunk into a fresh bytes object (what `read` costs, ~7 % of a streaming decode),
        and the words stay aligned. Leaves the file positioned after what it decoded."""
        start = self._f.tell()
        size = os.fstat(self._f.fileno()).st_size
        if size <= start:
            return
        try:
            mm = mmap.mmap(self._f.fileno(), size, access=mmap.ACCESS_READ)
        except (OSError, ValueError):  # not a mappable file (a pipe, a special file): read it
            return
        # the map closes with its last array (an error's traceback may hold one: closing it
        # here would replace that error with a BufferError)
        step = self.chunk_bytes
        for pos in range(start, size, step):
            yield self.decoder.feed(np.frombuffer(mm, np.uint8, min(step, size - pos), pos))
        self._f.seek(size)

    @property
    def stats(self) -> dict[str, int]:
        return self.decoder.stats

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> RawReader:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def read_raw(
    path: str | Path, *, strict: bool = False, fmt: str | None = None, jump_confirm: int = JUMP_CONFIRM
) -> tuple[RawHeader, Decoded]:
    """Decode a whole RAW file."""
    with Path(path).open("rb") as f:
        hdr = parse_raw_header(f)
        if fmt is not None:
            hdr.fmt = fmt
        dec = StreamDecoder(
            hdr.fmt,
            width=hdr.width,
            height=hdr.height,
            strict=strict,
            offset=hdr.size,
            jump_confirm=jump_confirm,
        )
        size = os.fstat(f.fileno()).st_size
        parts = []
        if size > hdr.size:
            # decode the page cache's pages in place (a read-only map): no fresh buffer to fault
            # in and fill, which cost about a tenth of a whole-file decode. The map is closed when
            # the last array on it goes (an error's traceback may hold one: closing it here
            # would replace the error with a BufferError).
            mm = mmap.mmap(f.fileno(), size, access=mmap.ACCESS_READ)
            parts.append(dec.feed(np.frombuffer(mm, np.uint8, size - hdr.size, hdr.size)))
            f.seek(size)
        rest = f.read()  # the file grew while being read: keep the tail too
        if rest:
            parts.append(dec.feed(rest))
    parts.append(dec.finish())
    out = parts[0]
    for more in parts[1:]:
        out = join_decoded(out, more)
    dec.log_stats()
    return hdr, out


def encode(fmt: str, events: EventArray, triggers: TriggerEvents | None = None) -> bytes:
    """One-shot encoding in any supported format."""
    if fmt == "evt3":
        return evt3.encode_evt3(events, triggers)
    if fmt == "evt2":
        return evt2.encode_evt2(events, triggers)
    if fmt in ("evt21", "evt21_le"):
        return evt21.encode_evt21(events, triggers, little_endian=fmt == "evt21_le")
    raise EventDataError(f"unknown EVT format {fmt!r}")


def write_raw(
    path: str | Path, header: RawHeader, events: EventArray, triggers: TriggerEvents | None = None
) -> None:
    """Write a RAW file that OpenEB and `read_raw` decode back to the same events."""
    if len(events) and (int(events.x.max()) >= header.width or int(events.y.max()) >= header.height):
        raise EventDataError(f"events exceed the header geometry {header.width}x{header.height}")
    payload = encode(header.fmt, events, triggers)
    with Path(path).open("wb") as f:
        f.write(header.to_bytes())
        f.write(payload)


def warm_up_decoder(fmt: str, width: int = 1280, height: int = 720) -> None:
    """Compile (or load from numba's cache) the stream decoder of `fmt` for the argument types a
    live stream gives it, so a take's first packets find it ready instead of waiting seconds for
    a cold JIT cache. A throwaway decoder is fed words of zeros cut mid-word (whatever they
    decode to, or are skipped as, is thrown away with it): numba compiles a kernel whole, so
    any words do."""
    decoder = StreamDecoder(fmt, width=width, height=height)
    data = bytes(64 * decoder._word + 1)
    decoder.feed(data[:33])
    decoder.feed(data[33:])
    if fmt == "evt3":
        # a capture that stores the words scans them (`scan`): its kernel compiles on the first
        # packet otherwise, seconds in the acquisition thread with the trigger already running
        StreamDecoder(fmt, width=width, height=height).scan(bytes(64 * decoder._word))
