"""The take list of the console: summaries, preview frames and event-rate series of finished takes.

Reading a take opens its HDF5 file, so results are cached per (path, size, mtime): a browser
refreshing the list every few seconds costs one `stat` per take, not a read. The take being
written is listed from its name only (it is open in the writer).
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, Field

from rigd.app.service.thumbnails import frame_thumbnail
from rigd.core.errors import RigdError
from rigd.take.reader import open_take

log = logging.getLogger(__name__)

#: Takes listed, newest first.
MAX_TAKES = 50
#: Bins of the event-rate plot of one sensor.
RATE_BINS = 120


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

    def __init__(self, take_dir: Path, thumbnail_width: int = 320) -> None:
        self.take_dir = take_dir
        self.width = thumbnail_width
        self._lock = threading.Lock()
        self._cache: dict[tuple[str, int, float], TakeEntry] = {}

    def path_of(self, name: str) -> Path:
        """The take called `name` in take_dir; refuses anything else (no path tricks)."""
        if "/" in name or "\\" in name or name.startswith(".") or not name.endswith(".h5"):
            raise RigdError(f"{name!r} is not a take name")
        path = self.take_dir / name
        if not path.is_file():
            raise RigdError(f"no take {name!r} in {self.take_dir}")
        return path

    def entries(self, running: str | None = None) -> list[TakeEntry]:
        try:
            files = sorted(self.take_dir.glob("*.h5"), key=lambda p: p.stat().st_mtime, reverse=True)
        except OSError as exc:
            raise RigdError(f"cannot list {self.take_dir}: {exc.strerror}") from exc
        out = []
        for path in files[:MAX_TAKES]:
            if running is not None and Path(running).name == path.name:
                st = path.stat()
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
        st = path.stat()
        key = (str(path), st.st_size, st.st_mtime)
        with self._lock:
            hit = self._cache.get(key)
        if hit is not None:
            return hit
        entry = _read_entry(path, st.st_size, st.st_mtime)
        with self._lock:
            self._cache = {k: v for k, v in self._cache.items() if k[0] != key[0]}
            self._cache[key] = entry
        return entry

    def preview(self, name: str, camera: str) -> bytes:
        """JPEG of the middle frame of one camera of a take."""
        with open_take(self.path_of(name)) as take:
            if camera not in take.cameras:
                raise RigdError(f"take {name} has no camera {camera!r}")
            frames = take.frames(camera)
            if len(frames) == 0:
                raise RigdError(f"take {name}: camera {camera} has no frames")
            jpeg, _, _ = frame_thumbnail(frames[len(frames) // 2], self.width)
            return jpeg

    def event_rates(self, name: str) -> dict[str, Any]:
        """Per sensor: events per second in RATE_BINS bins over its span (from ms_to_idx-backed
        index lookups, so no event is read)."""
        out: dict[str, Any] = {}
        with open_take(self.path_of(name)) as take:
            for sensor in take.event_sensors:
                span = take.event_span(sensor)
                if span is None or span[1] <= span[0]:
                    out[sensor] = {"t_s": [], "rate_hz": []}
                    continue
                edges = np.linspace(span[0], span[1] + 1, RATE_BINS + 1).astype(np.int64)
                idx = np.array([take.event_index(sensor, int(t)) for t in edges], np.int64)
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
