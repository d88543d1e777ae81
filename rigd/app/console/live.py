"""Rate-limited, latest-value publishing of the daemon's live state to the web console.

Why latest-value slots and not queues: the capture must not pay for browsers. One publisher
thread samples the daemon's telemetry and renders the JPEG previews at most `rate_hz` times a
second, and only while somebody watches; every browser then reads the newest value from a slot.
A slow browser simply skips versions (nothing is queued for it), and ten browsers cost the
capture what one does: one telemetry snapshot and one JPEG per device per tick.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Generic, Protocol, TypeVar

import numpy as np

from rigd.app.service.protocol import Telemetry
from rigd.app.service.thumbnails import events_thumbnail, frame_thumbnail
from rigd.core.events import EventArray
from rigd.core.frames import Frame

if TYPE_CHECKING:
    from rigd.app.service.daemon import Daemon

log = logging.getLogger(__name__)

T = TypeVar("T")

#: Highest publication rate of telemetry and previews (Hz).
DEFAULT_RATE_HZ = 5.0
#: The publisher sleeps when nobody asked for live data for this long (s).
IDLE_AFTER_S = 3.0
#: Span of the write rate shown (s): longer than the writer's flush interval.
RATE_WINDOW_S = 3.0
#: Event-frame windows a browser may choose (ms); the default is the first.
EVENT_WINDOWS_MS: tuple[int, ...] = (10, 20, 40)


class LatestSlot(Generic[T]):
    """One value and its version; writers replace it, readers get the newest (never a backlog)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._value: T | None = None
        self._version = 0

    def put(self, value: T) -> int:
        with self._lock:
            self._value = value
            self._version += 1
            return self._version

    def get(self) -> tuple[int, T | None]:
        with self._lock:
            return self._version, self._value


class LiveSource(Protocol):
    """What the publisher reads from the daemon (the Daemon satisfies it through `DaemonSource`)."""

    def telemetry(self) -> Telemetry: ...

    def latest_frames(self) -> dict[str, Frame]: ...

    def latest_events(self) -> dict[str, tuple[EventArray, tuple[int, int]]]: ...


@dataclass(frozen=True, slots=True)
class Preview:
    """A JPEG preview of one device and what it shows."""

    device: str
    kind: str
    jpeg: bytes
    width: int
    height: int
    window_ms: float | None = None
    time_utc: str = ""


@dataclass
class LiveState:
    """The slots the console reads: the telemetry document and one preview per device."""

    status: LatestSlot[dict[str, Any]] = field(default_factory=LatestSlot)
    previews: dict[str, LatestSlot[Preview]] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def preview_slot(self, device: str) -> LatestSlot[Preview]:
        with self.lock:
            slot = self.previews.get(device)
            if slot is None:
                slot = self.previews[device] = LatestSlot()
            return slot

    def preview_versions(self) -> dict[str, int]:
        with self.lock:
            slots = dict(self.previews)
        return {name: slot.get()[0] for name, slot in slots.items()}


def event_window(events: EventArray, window_ms: float) -> EventArray:
    """The last `window_ms` of `events` (by their own timestamps)."""
    if len(events) == 0:
        return events
    t_end = int(events.t.max())
    keep = np.flatnonzero(events.t >= t_end - int(window_ms * 1000))
    return events[keep]


class LivePublisher:
    """One thread: telemetry and previews into `state` at most `rate_hz`, only while watched."""

    def __init__(
        self,
        source: LiveSource,
        *,
        rate_hz: float = DEFAULT_RATE_HZ,
        thumbnail_width: int = 320,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if rate_hz <= 0:
            raise ValueError(f"rate_hz must be positive, got {rate_hz}")
        self.source = source
        self.state = LiveState()
        self.interval_s = 1.0 / rate_hz
        self.width = thumbnail_width
        self.event_window_ms: float = EVENT_WINDOWS_MS[0]
        self._clock = clock
        self._wanted = threading.Event()
        self._last_wanted = -1e9
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._written: deque[tuple[float, int]] = deque()
        self._tick_lock = threading.Lock()
        self._last_tick = -1e9
        self.ticks = 0
        self.idle_waits = 0

    def want(self) -> None:
        """A browser asked for live data: keep publishing for IDLE_AFTER_S more."""
        self._last_wanted = self._clock()
        self._wanted.set()

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="console-live", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._wanted.set()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def _run(self) -> None:
        while not self._stop.is_set():
            if self._clock() - self._last_wanted > IDLE_AFTER_S:
                self._wanted.clear()
                self.idle_waits += 1
                self._wanted.wait(0.2)  # nobody watches: cost nothing
                continue
            t0 = self._clock()
            try:
                with self._tick_lock:
                    self.tick()
            except Exception:
                # A failed tick (a session finishing under us) must not end live data; logged
                # with its traceback, and the next tick tries again.
                log.exception("console live tick failed")
            self._stop.wait(max(0.0, self.interval_s - (self._clock() - t0)))

    def fresh_status(self) -> dict[str, Any]:
        """The newest telemetry document, sampled now only if the last one is older than a tick."""
        self.want()
        with self._tick_lock:
            doc = self.state.status.get()[1]
            if doc is None or self._clock() - self._last_tick >= self.interval_s:
                self.tick()
                doc = self.state.status.get()[1]
        assert doc is not None
        return doc

    def tick(self) -> None:
        """Sample once: the telemetry document, then the previews of a running take."""
        t = self.source.telemetry()
        now = self._clock()
        self._last_tick = now
        t.write_rate_bytes_s = self._write_rate(now, t.bytes_written)
        doc = t.model_dump(mode="json")
        if t.state in ("capturing", "stopping"):
            self._previews(t.time_utc)
        doc["previews"] = self.state.preview_versions()
        doc["event_window_ms"] = self.event_window_ms
        self.state.status.put(doc)
        self.ticks += 1

    def _write_rate(self, now: float, written: int) -> float:
        """Bytes/s over the last RATE_WINDOW_S: the take file grows at each flush (1 s), so a rate
        between two 5 Hz ticks would be zero most of the time."""
        w = self._written
        if w and written < w[-1][1]:  # a new take
            w.clear()
        w.append((now, written))
        while len(w) > 2 and now - w[1][0] >= RATE_WINDOW_S:
            w.popleft()
        t0, b0 = w[0]
        return max(0.0, (written - b0) / (now - t0)) if now > t0 else 0.0

    def _previews(self, time_utc: str) -> None:
        for name, frame in self.source.latest_frames().items():
            jpeg, w, h = frame_thumbnail(frame, self.width)
            self.state.preview_slot(name).put(Preview(name, "rgb_camera", jpeg, w, h, None, time_utc))
        window = self.event_window_ms
        for name, (events, geometry) in self.source.latest_events().items():
            jpeg, w, h = events_thumbnail(event_window(events, window), geometry, self.width)
            self.state.preview_slot(name).put(Preview(name, "event_sensor", jpeg, w, h, window, time_utc))


class DaemonSource:
    """`LiveSource` over a running Daemon: its telemetry and its running session's latest data."""

    def __init__(self, daemon: Daemon) -> None:
        self._daemon = daemon

    def telemetry(self) -> Telemetry:
        return self._daemon.telemetry()

    def latest_frames(self) -> dict[str, Frame]:
        session = self._daemon.current_session()
        return {} if session is None else session.latest_frames()

    def latest_events(self) -> dict[str, tuple[EventArray, tuple[int, int]]]:
        session = self._daemon.current_session()
        return {} if session is None else session.latest_events()
