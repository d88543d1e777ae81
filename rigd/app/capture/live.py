"""Per-device live counters for telemetry, and the trigger observations the sync engine fits."""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from rigd.app.capture.results import DeviceSnapshot, DeviceState
from rigd.core.kinds import DeviceKind

#: Device rates in telemetry are averaged over this many seconds.
RATE_WINDOW_S = 2.0
#: Keep this many recent trigger observations per device for the live interval jitter.
JITTER_WINDOW = 64


@dataclass(slots=True)
class Observations:
    """Trigger observations kept in memory for the sync engine (small: one per pulse).

    Only what reached the file is kept, so the sync engine's per-frame pulse indices line
    up with the written frames."""

    t: list[int] = field(default_factory=list)
    host: list[int] = field(default_factory=list)
    counter: list[int] = field(default_factory=list)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return (
            np.asarray(self.t, np.int64),
            np.asarray(self.host, np.int64),
            np.asarray(self.counter, np.int64),
        )

    def interval_jitter_us(self, period_us: float) -> float | None:
        """Spread of the recent trigger intervals around whole periods (a noisy input shows)."""
        t = np.asarray(self.t[-JITTER_WINDOW - 1 :], np.int64)
        if t.size < 3:
            return None
        d = np.diff(t).astype(np.float64)
        m = np.maximum(np.rint(d / period_us), 1.0)
        return float(np.std(d - m * period_us))


@dataclass(slots=True)
class HostAnchors:
    """(device us, host ns) of data as it arrived, for a device with no trigger observations
    (an event sensor without trigger-in): per `BUCKET_NS` of host time only the fastest
    arrival is kept (least latency), so memory grows with the take's length, not its rate."""

    BUCKET_NS = 100_000_000
    best: dict[int, tuple[int, int]] = field(default_factory=dict)

    def note(self, t_device_us: int, host_ns: int) -> None:
        key = host_ns // self.BUCKET_NS
        old = self.best.get(key)
        if old is None or host_ns // 1000 - t_device_us < old[1] // 1000 - old[0]:
            self.best[key] = (t_device_us, host_ns)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        pairs = [self.best[k] for k in sorted(self.best)]
        return (
            np.asarray([p[0] for p in pairs], np.int64),
            np.asarray([p[1] for p in pairs], np.int64),
        )


@dataclass(slots=True)
class Gap:
    """A device away (unplugged, reconnecting) since `since_mono`."""

    since_mono: float
    t_before: int | None
    """The last device time delivered before the gap."""
    why: str


@dataclass(slots=True)
class LiveStats:
    """Counters the acquisition and writer threads update for telemetry."""

    kind: DeviceKind
    state: DeviceState = "ok"
    total: int = 0
    queued: int = 0
    reconnects: int = 0
    last_data_mono: float | None = None
    last_host_ns: int | None = None
    """Host arrival time of the newest delivery (monotonic ns), for the end-of-take drain."""
    rate_hz: float = 0.0
    samples: deque[tuple[float, int]] = field(default_factory=lambda: deque(maxlen=128))
    """(host monotonic s, total) a few times a second, for the rate over the last 2 s."""
    last_t: int | None = None
    """Device time of the newest item delivered."""
    gap: Gap | None = None
    lock: threading.Lock = field(default_factory=threading.Lock)

    def enqueued(self) -> None:
        with self.lock:
            self.queued += 1

    def dequeued(self) -> None:
        with self.lock:
            self.queued -= 1

    def update_rate(self, now: float) -> None:
        """Rate over the last ~2 s (sliding, so batched deliveries do not make it jump)."""
        samples = self.samples
        if not samples or now - samples[-1][0] >= 0.1:
            samples.append((now, self.total))
        while len(samples) > 2 and now - samples[1][0] >= RATE_WINDOW_S:
            samples.popleft()
        t0, n0 = samples[0]
        if now - t0 >= 0.3:
            self.rate_hz = (self.total - n0) / (now - t0)

    def snapshot(self, name: str, lost: int, jitter_us: float | None, shed: int = 0) -> DeviceSnapshot:
        age = None if self.last_data_mono is None else time.monotonic() - self.last_data_mono
        return DeviceSnapshot(
            name,
            self.kind,
            self.state,
            self.total,
            self.rate_hz,
            lost,
            self.reconnects,
            self.queued,
            age,
            jitter_us,
            shed,
        )
