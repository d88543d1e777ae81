"""The simulated world: true time, device clocks, the trigger wire and the ground truth.

Every simulated device of one rig shares a `SimWorld`. True time is the host's monotonic
clock (the sim runs in real time, so the daemon meets real deadlines); each device reads
it through its own `DeviceClock`, with an offset and a drift, and the ground truth of
everything the devices did is logged in true time so tests can score the sync engine.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class DeviceClock:
    """device_us = offset_us + true_us * (1 + drift_ppm * 1e-6), latched by flooring."""

    offset_us: float = 0.0
    drift_ppm: float = 0.0

    @property
    def rate(self) -> float:
        return 1.0 + self.drift_ppm * 1e-6

    def at(self, true_us: float) -> float:
        return self.offset_us + true_us * self.rate

    def stamp(self, true_us: float) -> int:
        """What the device's integer microsecond counter reads at a true time."""
        return math.floor(self.at(true_us))

    def true_at(self, device_us: float) -> float:
        return (device_us - self.offset_us) / self.rate


@dataclass(frozen=True, slots=True)
class Edge:
    """A transition on the trigger line, at a true time (jitter already applied)."""

    rising: bool
    true_us: float
    pulse_index: int


EdgeCallback = Callable[[Edge], None]


class TriggerWire:
    """The hardware trigger line: the box fires edges, devices listen."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._subscribers: list[EdgeCallback] = []

    def subscribe(self, callback: EdgeCallback) -> Callable[[], None]:
        with self._lock:
            self._subscribers.append(callback)

        def unsubscribe() -> None:
            with self._lock:
                if callback in self._subscribers:
                    self._subscribers.remove(callback)

        return unsubscribe

    def fire(self, edge: Edge) -> None:
        with self._lock:
            subscribers = list(self._subscribers)
        for cb in subscribers:
            cb(edge)


@dataclass(slots=True)
class GroundTruth:
    """What really happened, in true time, for tests to score against."""

    pulses: list[tuple[int, int, float, bool]] = field(default_factory=list)
    """(pulse index, box timestamp reported, true edge time, delivered on the wire)."""
    frames: dict[str, list[tuple[int, float, bool]]] = field(default_factory=dict)
    """camera -> (frame counter, true exposure start, delivered to host)."""
    clocks: dict[str, DeviceClock] = field(default_factory=dict)
    """device name -> its clock; the trigger box is under 'trigger'."""
    lock: threading.Lock = field(default_factory=threading.Lock)

    def add_pulse(self, index: int, box_us: int, true_us: float, delivered: bool) -> None:
        with self.lock:
            self.pulses.append((index, box_us, true_us, delivered))

    def add_frame(self, camera: str, counter: int, true_us: float, delivered: bool) -> None:
        with self.lock:
            self.frames.setdefault(camera, []).append((counter, true_us, delivered))

    def device_to_rig(self, device: str, device_us: float) -> float:
        """Exact rig (trigger box) time of a device timestamp."""
        true_us = self.clocks[device].true_at(device_us)
        return self.clocks["trigger"].at(true_us)


class SimWorld:
    """Shared state of one simulated rig."""

    def __init__(self, name: str = "default", seed: int = 0) -> None:
        self.name = name
        self.seed = seed
        self._epoch_ns = time.monotonic_ns()
        self.wire = TriggerWire()
        self.truth = GroundTruth()
        self._lock = threading.Lock()
        self._resources: dict[str, object] = {}

    def now_us(self) -> float:
        """True time in microseconds since the world was created."""
        return (time.monotonic_ns() - self._epoch_ns) / 1000.0

    def sleep_until(self, true_us: float, stop: threading.Event | None = None) -> bool:
        """Sleep until a true time; returns False if `stop` was set first."""
        while True:
            remaining = (true_us - self.now_us()) / 1e6
            if remaining <= 0:
                return True
            if stop is not None:
                if stop.wait(min(remaining, 0.05)):
                    return False
            else:
                time.sleep(min(remaining, 0.05))

    def register_clock(self, device: str, clock: DeviceClock) -> None:
        with self.truth.lock:
            self.truth.clocks[device] = clock

    def resource(self, key: str, make: Callable[[], object]) -> object:
        """A per-world singleton (the scene, say), made on first use."""
        with self._lock:
            if key not in self._resources:
                self._resources[key] = make()
            return self._resources[key]


_worlds: dict[str, SimWorld] = {}
_worlds_lock = threading.Lock()


def get_world(name: str = "default", seed: int = 0) -> SimWorld:
    """The world of that name, created on first use (the seed applies then)."""
    with _worlds_lock:
        world = _worlds.get(name)
        if world is None:
            world = _worlds[name] = SimWorld(name, seed)
        return world


def reset_world(name: str = "default") -> None:
    """Forget a world so the next `get_world` starts a fresh one (tests, repeated captures)."""
    with _worlds_lock:
        _worlds.pop(name, None)
