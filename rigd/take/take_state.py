"""The state of one open take file, shared by the writer that records it and the steps that end it.

`rigd.take.writer.TakeWriter` records into it (`add_*`, `append_*`, `flush`, `close`); the seal
(`rigd.take.seal`: finalize, fail, the recovery stamp) and `rigd.take.resume` (reopening a take
whose writer died) work on the same state, so the writer does not have to carry them.
"""

from __future__ import annotations

import logging
from pathlib import Path

import h5py

from rigd.core.errors import TakeError
from rigd.core.schema import SCHEMA_VERSION
from rigd.core.settings import WriterConfig
from rigd.take.event_store import EventStore
from rigd.take.finalize import FinalizePlan, Finalizer
from rigd.take.h5file import Syncer, compression_options
from rigd.take.refused import discard_pending_writes
from rigd.take.repair import Trim
from rigd.take.sinks import CameraSink, PulseSink

log = logging.getLogger(__name__)

#: Raw-data chunk cache of each dataset while writing (HDF5 2.0's default is 8 MiB): none. The
#: writer writes whole chunks (events, one frame per chunk) and appends rows once a flush, so a
#: cache only holds data back: dirty chunks that a full disk leaves nowhere to go when the take
#: is marked failed and closed (the ballast would have to cover them). Worse, HDF5 notes where a
#: cached chunk goes before writing it and indexes it only after: when that write fails (disk
#: full), the retry a fail makes in the ballast's room writes the chunk but never indexes it, and
#: it reads back as zeros (columns storage: a whole chunk of event times, silently). Uncached,
#: a write fails at the call that made it, and its retry is indexed (tests/rigd/take/test_evt_words.py).
WRITE_CHUNK_CACHE_BYTES = 0


class TakeState:
    """One open take: its file, its per-device stores and where it stands.

    `status` is "recording", "finalizing" (a finalize has started; `plan` holds its maps),
    "complete" or "failed".
    """

    def __init__(
        self, path: Path, f: h5py.File, config: WriterConfig, pulses: PulseSink, *, status: str
    ) -> None:
        self.path = path
        self.f = f
        self.config = config
        self.event_opts = compression_options(config.event_compression, shuffle=True)
        # Derived datasets written on finalize (ms_to_idx). The small per-item series (frame
        # times, triggers, pulses) are stored uncompressed: their last chunk is rewritten on
        # every flush, and only a fixed-size chunk is rewritten in place (see rigd.take.tails).
        self.small_opts = compression_options(config.event_compression, shuffle=True)
        self.frame_opts = compression_options(config.frame_compression, shuffle=False)
        self.pulses = pulses
        self.status = status
        self.closed = False
        self.refused: OSError | None = None
        """What the file refused when the take was failed (then closing writes nothing)."""
        self.syncer = Syncer(path.name)
        self.version = SCHEMA_VERSION
        """Of the file: a resumed take keeps the version it was written with."""
        self.has_trigger = False
        self.stores: dict[str, EventStore] = {}
        self.cameras: dict[str, CameraSink] = {}
        self.flush_count = 0
        self.flush_seconds_total = 0.0
        """Time spent in flushes (with `fsync`, the wait for the disk too)."""
        self.flush_seconds_max = 0.0
        self.plan: FinalizePlan | None = None
        """The stored finalize plan, once a finalize has started."""
        self.repairs: list[Trim] = []
        """What resuming trimmed (empty for a new take or an undamaged one)."""

    @property
    def finalize_pending(self) -> bool:
        """A resumed take whose finalize had started: it is to be continued, not restarted."""
        return self.plan is not None and self.status == "finalizing"

    def check_open(self) -> None:
        if self.closed:
            raise TakeError(f"{self.path}: take is closed")

    def check_writable(self) -> None:
        self.check_open()
        if self.status != "recording":
            raise TakeError(f"{self.path}: take is {self.status}; no more data can be written")

    def write_all(self, *, final: bool = True) -> None:
        """Write every buffer: events up to the last whole chunk and the rest to their tail
        (a flush), or all of it to the main datasets (`final`: close, fail, finalize)."""
        for store in self.stores.values():
            store.write_buffers(final=final)
        for cam in self.cameras.values():
            cam.write_series()
            cam.trim_images()
        self.pulses.write()

    def drop_tails(self) -> None:
        for store in self.stores.values():
            store.drop_tails()

    def drop_tails_after_flush(self) -> None:
        self.f.flush()  # the tails are redundant only once the main data is on disk
        self.drop_tails()

    def discard_pending(self) -> None:
        """Let HDF5 close a file it failed to write (rigd.take.refused)."""
        try:
            self.syncer.wait()  # not on a file descriptor about to be swapped
        except OSError as exc:
            log.error("take %s: the last flush's fsync failed too: %s", self.path, exc)
        discard_pending_writes(self.f, self.path)

    def finalizer(self) -> Finalizer:
        return Finalizer(
            self.f,
            self.path,
            self.stores,
            self.cameras,
            event_opts=self.event_opts,
            small_opts=self.small_opts,
        )
