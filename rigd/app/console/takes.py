"""The take list of the console: summaries, preview frames and event-rate series of finished takes.

Reading a take opens its HDF5 file, so results are cached per (path, size, mtime): a browser
refreshing the list every few seconds costs one `stat` per take, not a read. The take being
written is listed from its name only (it is open in the writer).

Whoever can write into take_dir must not make the console read or write elsewhere: a symlink
there (named like a take, or a notes or calibration file) is never followed, and a name is
only ever looked up as a plain file directly in its directory (`file_in`).
"""

from __future__ import annotations

import logging
import os
import stat
import threading
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, Field

from rigd.app.service.requests import printable
from rigd.app.service.thumbnails import frame_thumbnail
from rigd.core.errors import RigdError, TakeError, TakeFormatError
from rigd.take.isolated import READ_TIMEOUT_S, run_isolated
from rigd.take.reader import open_take

log = logging.getLogger(__name__)

#: Takes listed, newest first.
MAX_TAKES = 50
#: Bins of the event-rate plot of one sensor.
RATE_BINS = 120
#: Longest file name the console looks up (file systems allow 255 bytes).
MAX_NAME_CHARS = 200


def check_name(name: str, what: str = "file") -> None:
    """Refuse a name that is not one plain file name: too long, a path, hidden, or not text."""
    shown = repr(name[:60]) + ("..." if len(name) > 60 else "")
    if len(name) > MAX_NAME_CHARS:
        raise RigdError(f"{what} name {shown} has {len(name)} characters; the limit is {MAX_NAME_CHARS}")
    if not name or "/" in name or "\\" in name or "\x00" in name or name.startswith("."):
        raise RigdError(f"{shown} is not a {what} name")
    if not _utf8(name):
        raise RigdError(f"{shown} is not a {what} name (not valid Unicode)")


def file_in(directory: Path, name: str, what: str = "file") -> Path:
    """`directory/name` when it is a plain file right there: not a symlink, not a path that
    resolves outside `directory`; RigdError (saying why) otherwise."""
    check_name(name, what)
    path = directory / name
    try:
        st = path.lstat()
    except FileNotFoundError:
        raise RigdError(f"no {what} {name!r} in {directory}") from None
    except OSError as exc:
        raise RigdError(f"{what} {name!r}: {exc.strerror}") from None
    if stat.S_ISLNK(st.st_mode):
        raise RigdError(f"{what} {name!r} is a symbolic link; the console does not follow links")
    if not stat.S_ISREG(st.st_mode):
        raise RigdError(f"{what} {name!r} is not a regular file")
    if path.resolve().parent != directory.resolve():
        raise RigdError(f"{what} {name!r} is not in {directory}")
    return path


def _utf8(text: str) -> bool:
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def plain_dir(directory: Path, what: str) -> Path:
    """`directory` when it is a real directory (not a symlink to one); RigdError otherwise."""
    try:
        st = directory.lstat()
    except OSError as exc:
        raise RigdError(f"{what} {directory}: {exc.strerror}") from None
    if stat.S_ISLNK(st.st_mode):
        raise RigdError(f"{what} {directory} is a symbolic link; the console does not follow links")
    if not stat.S_ISDIR(st.st_mode):
        raise RigdError(f"{what} {directory} is not a directory")
    return directory


def read_text_nofollow(path: Path, limit: int) -> str | None:
    """The text of `path` (at most `limit` bytes), or None when there is none; never through a
    symlink (OSError ELOOP) and never from anything but a regular file."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except FileNotFoundError:
        return None
    with os.fdopen(fd, "rb") as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            raise OSError(f"{path} is not a regular file")
        return f.read(limit).decode("utf-8", "replace")


def write_text_nofollow(path: Path, text: str) -> None:
    """Write `text` to `path`, never through a symlink (OSError ELOOP when `path` is one) and
    only into a regular file (a FIFO planted there fails at once instead of blocking)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW | os.O_NONBLOCK, 0o666)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            raise OSError(f"{path} is not a regular file")
        f.write(text)


class TakeEntry(BaseModel):
    """One take in the console's list, with what the operator must do about it."""

    name: str
    path: str
    size_bytes: int
    mtime: float
    status: str = Field(description="complete, recording (unfinished), failed, unreadable or running")
    verdict: str | None = Field(
        None,
        description="complete (nothing lost), degraded (sealed but lost data), failed or unfinished "
        "(rigd.take.verdict); None while running or when unreadable.",
    )
    verdict_reasons: list[str] = Field(default_factory=list, description="Why the verdict is not complete.")
    end_reason: str | None = None
    recovered: bool = False
    frames: dict[str, int] = Field(default_factory=dict)
    events: dict[str, int] = Field(default_factory=dict)
    cameras: list[str] = Field(default_factory=list)
    event_sensors: list[str] = Field(default_factory=list)
    pulses: int = 0
    losses: int = 0
    warnings: list[str] = Field(default_factory=list)
    error: str | None = None
    action: str | None = Field(None, description="What the take needs, in words (e.g. run rigd recover).")


class TakeList:
    """Lists `take_dir` and reads takes on demand (cached, thread-safe)."""

    def __init__(
        self, take_dir: Path, thumbnail_width: int = 320, read_timeout_s: float = READ_TIMEOUT_S
    ) -> None:
        self.take_dir = take_dir
        self.width = thumbnail_width
        #: Each take is read in a worker process with this deadline (rigd.take.isolated): a
        #: take whose read hangs costs that take, never a thread of the daemon.
        self.read_timeout_s = read_timeout_s
        self._lock = threading.Lock()
        self._cache: dict[tuple[str, int, float], TakeEntry] = {}
        self._skipped: set[str] = set()

    def path_of(self, name: str) -> Path:
        """The take called `name` in take_dir; refuses anything else (no path tricks, no links)."""
        check_name(name, "take")
        if not name.endswith(".h5"):
            raise RigdError(f"{name!r} is not a take name")
        return file_in(self.take_dir, name, "take")

    def _takes(self) -> list[tuple[Path, os.stat_result]]:
        """The plain `*.h5` files of take_dir with their lstat; a symlink or anything else named
        like a take is left out (and said so in the log, once per name)."""
        out = []
        for path in self.take_dir.glob("*.h5"):
            try:
                st = path.lstat()
            except FileNotFoundError:  # removed while listing
                continue
            if not stat.S_ISREG(st.st_mode):
                why = "is a symbolic link" if stat.S_ISLNK(st.st_mode) else "is not a regular file"
            elif not _utf8(path.name):
                why = "has a name that is not UTF-8"
            else:
                out.append((path, st))
                continue
            if path.name not in self._skipped:
                self._skipped.add(path.name)
                log.warning("console: %s in %s %s; not listed", printable(path.name), self.take_dir, why)
        return out

    def entries(self, running: str | None = None) -> list[TakeEntry]:
        try:
            files = sorted(self._takes(), key=lambda p: p[1].st_mtime, reverse=True)
        except OSError as exc:
            raise RigdError(f"cannot list {self.take_dir}: {exc.strerror}") from exc
        out = []
        for path, st in files[:MAX_TAKES]:
            if running is not None and Path(running).name == path.name:
                out.append(
                    TakeEntry(
                        name=path.name,
                        path=str(path),
                        size_bytes=st.st_size,
                        mtime=st.st_mtime,
                        status="running",
                    )
                )
                continue
            out.append(self.entry(path))
        return out

    def entry(self, path: Path) -> TakeEntry:
        st = path.lstat()
        key = (str(path), st.st_size, st.st_mtime)
        with self._lock:
            hit = self._cache.get(key)
        if hit is not None:
            return hit
        try:
            entry = run_isolated(
                _read_entry, path, st.st_size, st.st_mtime, timeout_s=self.read_timeout_s, what=str(path)
            )
        except TakeError as exc:  # the worker hung (killed) or died: listed as unreadable
            entry = TakeEntry(
                name=path.name,
                path=str(path),
                size_bytes=st.st_size,
                mtime=st.st_mtime,
                status="unreadable",
                error=str(exc),
                action="reading this file hangs or crashes its reader: move it out of the take directory",
            )
        with self._lock:
            self._cache = {k: v for k, v in self._cache.items() if k[0] != key[0]}
            self._cache[key] = entry
        return entry

    def preview(self, name: str, camera: str) -> bytes:
        """JPEG of the middle frame of one camera of a take (read in a worker with a deadline)."""
        path = self.path_of(name)
        return run_isolated(
            _preview, path, name, camera, self.width, timeout_s=self.read_timeout_s, what=str(path)
        )

    def event_rates(self, name: str) -> dict[str, Any]:
        """Per sensor: events per second in RATE_BINS bins over its span (from ms_to_idx-backed
        index lookups, so no event is read); read in a worker with a deadline."""
        path = self.path_of(name)
        return run_isolated(_event_rates, path, timeout_s=self.read_timeout_s, what=str(path))


def _preview(path: Path, name: str, camera: str, width: int) -> bytes:
    with open_take(path) as take:
        if camera not in take.cameras:
            raise RigdError(f"take {name} has no camera {camera!r}")
        frames = take.camera(camera)
        if len(frames) == 0:
            raise RigdError(f"take {name}: camera {camera} has no frames")
        jpeg, _, _ = frame_thumbnail(frames[len(frames) // 2], width)
        return jpeg


def _event_rates(path: Path) -> dict[str, Any]:
    out: dict[str, Any] = {}
    with open_take(path) as take:
        for sensor in take.event_sensors:
            series = take.sensor(sensor)
            span = series.span
            if span is None or span[1] <= span[0]:
                out[sensor] = {"t_s": [], "rate_hz": []}
                continue
            edges = np.linspace(span[0], span[1] + 1, RATE_BINS + 1).astype(np.int64)
            idx = np.array([series.index(int(t)) for t in edges], np.int64)
            dt_s = np.diff(edges) / 1e6
            out[sensor] = {
                "t_s": ((edges[:-1] - edges[0]) / 1e6).round(4).tolist(),
                "rate_hz": (np.diff(idx) / dt_s).round(1).tolist(),
            }
    return out


def _read_entry(path: Path, size: int, mtime: float) -> TakeEntry:
    base: dict[str, Any] = {"name": path.name, "path": str(path), "size_bytes": size, "mtime": mtime}
    try:
        with open_take(path) as take:
            s = take.summary()
    except TakeFormatError as exc:  # breaks the format's rules: listed as damaged, nothing trusted
        log.info("console: take %s damaged: %s", path, exc)
        return TakeEntry(
            **base,
            status="unreadable",
            verdict="damaged",
            verdict_reasons=[str(exc)],
            error=str(exc),
            action="the file breaks the take format (docs/take-format.md): it is not read; "
            f"`rigd recover {path}` says whether anything in it can be saved",
        )
    except (RigdError, OSError) as exc:
        log.info("console: take %s not readable: %s", path, exc)
        return TakeEntry(
            **base,
            status="unreadable",
            error=str(exc),
            action=f"run `rigd recover {path}`: it seals a take a crash left unfinished, "
            "or says why the file cannot be read",
        )
    action = None
    if s.status == "recording":
        action = f"unfinished (its writer stopped): run `rigd recover {path}` to seal it"
    elif s.status == "failed":
        action = (
            f"failed ({s.failure_reason or 'see its log'}): data up to the last flush is readable; "
            f"`rigd recover {path}` seals it once the cause (e.g. a full disk) is fixed"
        )
    return TakeEntry(
        **base,
        status=s.status,
        verdict=s.verdict,
        verdict_reasons=s.verdict_reasons,
        end_reason=s.end_reason,
        recovered=s.recovered_utc is not None,
        frames={k: v.frames for k, v in s.cameras.items()},
        events={k: v.events for k, v in s.event_sensors.items()},
        cameras=list(s.cameras),
        event_sensors=list(s.event_sensors),
        pulses=s.pulses,
        losses=len(s.losses),
        warnings=s.warnings[:5],
        error=s.failure_reason,
        action=action,
    )
