"""The simulated world: true time, device clocks, the trigger wire and the ground truth.

Every simulated device of one rig shares a `SimWorld`. True time is the world's clock
(`firmware_sim.clock`): the host's monotonic clock by default, so the daemon meets real
deadlines, or a virtual clock (`clock=virtual`) that runs as fast as the CPU allows and gives
the same data twice; each device reads it through its own `DeviceClock`, with an offset and
a drift, and the ground truth of everything the devices did is logged in true time so tests
can score the sync engine. The world also owns the host clock its devices stamp what they hand
to the host with (`host_clock`): on virtual time, host time is virtual too.

Faults that must outlive one device object live here too: an unplugged device's window
(`UnplugFault`) is kept per device name, because the host recovers by opening the same spec
again. A world may be one end of the simulated trigger cable (`firmware_sim.cable`): its wire
and clock then reach the worlds of the same name in other processes. With `RIGD_SIM_TRUTH_LOG`
set, what the devices hand to the host is also appended to a JSON-lines journal (`TruthJournal`)
that survives a SIGKILL of the process (docs/sim-faults.md).
"""

from __future__ import annotations

import logging
import math
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from firmware_sim.cable import CableParams, parse_cable
from firmware_sim.clock import (
    CLOCK_MODES,
    ClockMode,
    Hold,
    RealClock,
    VirtualClock,
    make_clock,
    make_host_clock,
)
from rigd.core.errors import ConfigError, DeviceError
from rigd.core.host_clock import HostClock

if TYPE_CHECKING:
    from drivers.lifecycle import DeliveryQueue
    from drivers.registry import DeviceSpec
    from firmware_sim.cable_link import CableFollower, CableLead

log = logging.getLogger(__name__)

#: How often (wall s) a device waiting for room in its buffer looks whether to give up.
_ROOM_POLL_S = 0.05
#: Environment variable naming the ground-truth journal file (JSON lines, appended).
TRUTH_LOG_ENV = "RIGD_SIM_TRUTH_LOG"


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
    unplugged: dict[str, list[tuple[float, float]]] = field(default_factory=dict)
    """device -> (true_t_first, true_t_last) spans whose data never reached the host because the
    device was unplugged (`unplug_at_s`). Event sensors: from the end of the last slice the host
    read to the replug; cameras: the unplugged window (its lost frames are also in `frames`)."""
    ignored_triggers: dict[str, list[tuple[int, float]]] = field(default_factory=dict)
    """camera -> (pulse index, true edge time) of rising edges it ignored while busy (`busy_us`)."""
    lock: threading.Lock = field(default_factory=threading.Lock)

    def add_pulse(self, index: int, box_us: int, true_us: float, delivered: bool) -> None:
        with self.lock:
            self.pulses.append((index, box_us, true_us, delivered))

    def add_frame(self, camera: str, counter: int, true_us: float, delivered: bool) -> None:
        with self.lock:
            self.frames.setdefault(camera, []).append((counter, true_us, delivered))

    def mark_frames_lost(self, camera: str, counters: list[int]) -> None:
        """Frames logged as delivered that the host never got (left in an unplugged camera)."""
        if not counters:
            return
        todo = set(counters)
        with self.lock:
            rows = self.frames.get(camera, [])
            for i in range(len(rows) - 1, -1, -1):  # newest first: counters may repeat after a reset
                counter, true_us, delivered = rows[i]
                if counter in todo and delivered:
                    rows[i] = (counter, true_us, False)
                    todo.discard(counter)
                    if not todo:
                        break
        if todo:
            log.warning("truth: camera %s frames %s were never logged", camera, sorted(todo))

    def add_unplugged(self, device: str, true_first_us: float, true_last_us: float) -> None:
        with self.lock:
            self.unplugged.setdefault(device, []).append((true_first_us, true_last_us))

    def add_ignored_trigger(self, camera: str, pulse_index: int, true_us: float) -> None:
        with self.lock:
            self.ignored_triggers.setdefault(camera, []).append((pulse_index, true_us))


class SimWorld:
    """Shared state of one simulated rig."""

    def __init__(self, name: str = "default", seed: int = 0, clock: ClockMode = "real") -> None:
        self.name = name
        self.seed = seed
        self.clock: RealClock | VirtualClock = make_clock(clock)
        self.host_clock: HostClock = make_host_clock(self.clock)
        """What every device of this world stamps `host_time_ns` with: the host's monotonic
        clock in real time, epoch + virtual time on the virtual clock (`firmware_sim.clock`)."""
        self.wire = TriggerWire()
        self.truth = GroundTruth()
        self._lock = threading.Lock()
        self._resources: dict[str, object] = {}
        self._unplugs: dict[str, UnplugFault] = {}
        #: This world's end of the trigger cable, if its specs give one (`firmware_sim.cable`).
        self.cable: CableLead | CableFollower | None = None
        self.cable_params: CableParams | None = None

    @property
    def virtual(self) -> bool:
        return self.clock.mode == "virtual"

    def now_us(self) -> float:
        """True time in microseconds since the world was created (or its virtual clock's)."""
        return self.clock.now_us()

    def sleep_until(self, true_us: float, stop: threading.Event | None = None) -> bool:
        """Sleep until a true time without holding it; returns False if `stop` was set first."""
        return self.clock.sleep_until(true_us, stop)

    def hold(self) -> Hold:
        """Hold true time still while a device works (a no-op in real time)."""
        return self.clock.hold()

    def await_cable(self) -> None:
        """Before the world's time starts (the box's START): a cable lead waits, bounded, for
        its followers; DeviceError naming the cable if they do not come."""
        if self.cable is not None:
            self.cable.before_start()

    def connect_cable(self, params: CableParams) -> None:
        """Become the lead (listen) or a follower (connect, adopt the lead's time) of a cable."""
        from firmware_sim.cable_link import CableFollower, CableLead

        self.cable_params = params
        self.cable = CableLead(self, params) if params.role == "lead" else CableFollower(self, params)

    def close_cable(self) -> None:
        if self.cable is not None:
            self.cable.close()

    def register_clock(self, device: str, clock: DeviceClock) -> None:
        with self.truth.lock:
            self.truth.clocks[device] = clock

    def resource(self, key: str, make: Callable[[], object]) -> object:
        """A per-world singleton (the scene, say), made on first use."""
        with self._lock:
            if key not in self._resources:
                self._resources[key] = make()
            return self._resources[key]

    def unplug_fault(self, device: str) -> UnplugFault:
        """The unplug state of a device name, shared by every object opened under that name."""
        with self._lock:
            fault = self._unplugs.get(device)
            if fault is None:
                fault = self._unplugs[device] = UnplugFault(self, device)
            return fault


@dataclass(frozen=True, slots=True)
class UnplugParams:
    """`unplug_at_s` / `unplug_for_s` of a device spec (seconds of true time)."""

    at_s: float
    for_s: float = math.inf
    """math.inf: the device never comes back."""


def unplug_params(spec: DeviceSpec) -> UnplugParams | None:
    """Parse and check the unplug fault parameters of a spec; None when it has none."""
    if "unplug_at_s" not in spec.params:
        if "unplug_for_s" in spec.params:
            raise ConfigError(f"device spec {spec.raw!r}: unplug_for_s needs unplug_at_s")
        return None
    at_s = spec.float_param("unplug_at_s", 0.0)
    if not (math.isfinite(at_s) and at_s >= 0):
        raise ConfigError(
            f"device spec {spec.raw!r}: unplug_at_s={spec.params['unplug_at_s']!r} must be a finite "
            "number of seconds >= 0"
        )
    for_s = spec.float_param("unplug_for_s", math.inf)
    if not (for_s > 0):  # also rejects nan; inf (never replugged) is allowed
        raise ConfigError(
            f"device spec {spec.raw!r}: unplug_for_s={spec.params['unplug_for_s']!r} must be > 0 seconds"
        )
    return UnplugParams(at_s, for_s)


def power_on_clock(spec: DeviceSpec, world: SimWorld, name: str, clock: DeviceClock) -> DeviceClock:
    """`clock_reset=1`: a device opened after its replug counts from 0 again (most cameras and
    event sensors reset their timestamp counter on a power cycle); the crystal, so the drift,
    stays the same."""
    reset = spec.int_param("clock_reset", 0)
    if reset not in (0, 1):
        raise ConfigError(f"device spec {spec.raw!r}: clock_reset={reset!r} (use 0 or 1)")
    fault = world.unplug_fault(name)
    if reset == 0 or not fault.replugged_before(world.now_us()):
        return clock
    return DeviceClock(clock.offset_us - clock.at(fault.end_us), clock.drift_ppm)


class UnplugFault:
    """One device's unplug/replug window, kept by the world so that it outlives the device object.

    The host recovers from an unplug by closing the dead handle and opening the same spec again,
    so the window must belong to the device name: while it is open, opening fails as for a
    missing USB device; once it has happened it is never armed again. A device object opened
    before the window is dead from its start on, for good (its handle went stale, as on
    hardware), even after the replug. At the start a timer calls the listeners (the open device
    objects) so they can log what they lose at that instant; every check is also made against
    true time, so a late timer never lets data through.
    """

    def __init__(self, world: SimWorld, device: str) -> None:
        self._world = world
        self.device = device
        self._lock = threading.Lock()
        self.armed = False
        self.start_us = math.inf
        self.end_us = math.inf
        #: Camera frame counter to resume from after the replug (written by the camera).
        self.resume_counter = 0
        #: A camera acquiring on hardware trigger: rising edges in the window are lost frames.
        self.acquiring = False
        self._listeners: list[Callable[[], None]] = []
        self._unsubscribe_wire: Callable[[], None] | None = None

    def arm(self, start_us: float, end_us: float, *, lost_frames_on_edges: bool) -> bool:
        """Schedule the window [start_us, end_us) of true time; False if it was armed before."""
        with self._lock:
            if self.armed:
                return False
            self.armed = True
            # End first: unlocked readers never see a window that is open forever.
            self.end_us = end_us
            self.start_us = start_us
        # The USB disconnect "interrupt", for the device objects to log what they lose.
        self._world.clock.call_at(start_us, self._fire, f"sim-unplug-{self._world.name}-{self.device}")
        if lost_frames_on_edges:
            self._unsubscribe_wire = self._world.wire.subscribe(self._on_edge)
        log.info(
            "sim %s/%s: unplug armed for true %.0f..%.0f us",
            self._world.name,
            self.device,
            start_us,
            end_us,
        )
        return True

    def absent_at(self, true_us: float) -> bool:
        """Is the device unplugged (not on the bus) at this true time?"""
        return self.start_us <= true_us < self.end_us

    def kills(self, opened_us: float, true_us: float) -> bool:
        """Is a device object opened at `opened_us` dead (unplugged under it) at `true_us`?"""
        return opened_us <= self.start_us <= true_us

    def replugged_before(self, true_us: float) -> bool:
        """Did the window close before this true time (an object opened now is the replugged one)?"""
        return self.armed and self.end_us <= true_us

    def check_present(self, spec: str) -> None:
        """Refuse to open while unplugged, as a backend finds no such device."""
        now = self._world.now_us()
        if self.absent_at(now):
            back = "never" if math.isinf(self.end_us) else f"in {(self.end_us - now) / 1e6:.3f} s"
            raise DeviceError(f"cannot open {spec}: no such device (unplugged; back {back})")

    def listen(self, callback: Callable[[], None]) -> Callable[[], None]:
        """Call `callback` (on a timer thread) when the device is unplugged; returns the unsubscriber."""
        with self._lock:
            self._listeners.append(callback)

        def unlisten() -> None:
            with self._lock:
                if callback in self._listeners:
                    self._listeners.remove(callback)

        return unlisten

    def _fire(self) -> None:
        log.warning("sim %s/%s: unplugged", self._world.name, self.device)
        with self._lock:
            listeners = list(self._listeners)
        for cb in listeners:
            cb()

    def _on_edge(self, edge: Edge) -> None:
        """Rising edges in the window are frames an acquiring camera would have taken."""
        if not edge.rising or edge.true_us < self.start_us:
            return
        if edge.true_us >= self.end_us:
            unsubscribe, self._unsubscribe_wire = self._unsubscribe_wire, None
            if unsubscribe is not None:
                unsubscribe()
            return
        if self.acquiring:
            self._world.truth.add_frame(self.device, -1, edge.true_us, delivered=False)


class TruthJournal:
    """Append-only JSON-lines log of what the sim devices handed to the host, for crash tests.

    Each line is one `os.write` on an O_APPEND descriptor: the kernel appends it whole, so a
    SIGKILL can lose only lines not yet written, never tear one, and nothing waits in a
    Python buffer. Lines are built with f-strings (every value is a number or a name quoted
    once with json.dumps), which keeps the cost to a few microseconds per line.
    """

    def __init__(self, path: str) -> None:
        self.path = path
        self._fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC, 0o644)
        log.info("sim ground-truth journal: %s", path)

    def write(self, line: str) -> None:
        """Append one line (no newline in `line`); raises OSError if the disk refuses it."""
        data = (line + "\n").encode()
        n = os.write(self._fd, data)
        if n != len(data):  # a regular file only writes short when the disk is full
            raise OSError(f"truth journal {self.path}: short write ({n} of {len(data)} bytes)")

    def close(self) -> None:
        os.close(self._fd)


_journals: dict[str, TruthJournal] = {}
_journals_lock = threading.Lock()


def truth_journal() -> TruthJournal | None:
    """The journal `RIGD_SIM_TRUTH_LOG` names now (one descriptor per path), or None if unset.

    Devices look it up when they are opened, so a test may set the variable per test.
    """
    path = os.environ.get(TRUTH_LOG_ENV)
    if not path:
        return None
    with _journals_lock:
        journal = _journals.get(path)
        if journal is None:
            journal = _journals[path] = TruthJournal(path)
        return journal


def close_truth_journals() -> None:
    """Close every journal descriptor (tests); devices opened later reopen their path."""
    with _journals_lock:
        journals = list(_journals.values())
        _journals.clear()
    for journal in journals:
        journal.close()


def wait_for_room(queue: DeliveryQueue[Any], below: int, give_up: Callable[[], bool]) -> None:
    """On virtual time a device waits for its reader to make room in its buffer (fewer than
    `below` items queued) instead of losing data; it stops waiting once `give_up()` (stopped,
    unplugged) and the caller's put then counts what a full buffer costs."""
    while not queue.wait_room(_ROOM_POLL_S, below=below):
        if give_up():
            return


_worlds: dict[str, SimWorld] = {}
_worlds_lock = threading.Lock()


def get_world(
    name: str = "default", seed: int = 0, clock: str | None = None, cable: CableParams | None = None
) -> SimWorld:
    """The world of that name, created on first use (the seed, clock and cable end apply then;
    a spec that asks for another clock than the world runs on is refused, `spec_world` checks
    the cable). A follower world whose lead hung up is replaced by a fresh one."""
    if clock is not None and clock not in CLOCK_MODES:
        raise ConfigError(f"sim world {name!r}: clock={clock!r} (use {' or '.join(CLOCK_MODES)})")
    with _worlds_lock:
        world = _worlds.get(name)
        if world is not None and _spent(world):
            log.info("sim world %r: its cable's lead hung up; a fresh world connects again", name)
            world = None
        if world is None:
            mode: ClockMode = "virtual" if clock == "virtual" else "real"
            world = SimWorld(name, seed, mode)
            if cable is not None:
                world.connect_cable(cable)  # raises before the world is kept
            _worlds[name] = world
            return world
        if clock is not None and clock != world.clock.mode:
            raise ConfigError(
                f"sim world {name!r} runs on the {world.clock.mode} clock; a device spec asks for "
                f"clock={clock} (give every device of a world the same clock=)"
            )
        return world


def _spent(world: SimWorld) -> bool:
    """A follower world whose lead hung up can never move again."""
    return world.cable is not None and world.cable.dead


def spec_world(spec: DeviceSpec) -> SimWorld:
    """The world a sim spec names (`sim://WORLD/...?seed=&clock=real|virtual&cable=...`); every
    spec of a world must give the same cable parameters (none, or the same end)."""
    name = spec.location or "default"
    cable = parse_cable(spec)
    world = get_world(name, spec.int_param("seed", 0), spec.params.get("clock"), cable)
    if world.cable_params != cable:
        ours = world.cable_params
        param = ours.disagreement(cable) if ours is not None else "cable"
        theirs = world.cable_params
        raise ConfigError(
            f"device spec {spec.raw!r}: sim world {name!r} was opened with "
            f"{_cable_text(theirs)}; this spec gives {_cable_text(cable)} (they differ in {param}; "
            "give every device of a world the same cable parameters)"
        )
    return world


def _cable_text(params: CableParams | None) -> str:
    if params is None:
        return "no cable"
    text = f"cable={params.path} cable_role={params.role}"
    if params.role == "lead":
        text += f" cable_followers={params.followers}"
    if params.wait_s is not None:
        text += f" cable_wait_s={params.wait_s:g}"
    if params.stall_s is not None:
        text += f" cable_stall_s={params.stall_s:g}"
    return text


def reset_world(name: str = "default") -> None:
    """Forget a world so the next `get_world` starts a fresh one (tests, repeated captures);
    its cable end is closed."""
    with _worlds_lock:
        world = _worlds.pop(name, None)
    if world is not None:
        world.close_cable()


class Unpluggable:
    """The unplug fault's host-facing behaviour, shared by the sim camera and event sensor:
    once its window opens, this device object is stale for good and every call says so
    (through the `_check_present` hook of the device base classes)."""

    _fault: UnplugFault
    host_clock: HostClock
    _opened_us: float
    _world: SimWorld
    _lock: threading.Lock
    _name: str
    _device_label: str

    def _note_unplug_locked(self, lost: list[Any]) -> None:
        raise NotImplementedError

    def _plug_in(self, world: SimWorld, name: str, spec: str) -> None:
        """Take the device name's unplug fault (refusing to open while it is unplugged) and
        note when this object was opened: an unplug after that kills it for good."""
        self.host_clock = world.host_clock  # what it stamps host times with (Device.host_clock)
        self._fault = world.unplug_fault(name)
        self._fault.check_present(spec)
        self._opened_us = world.now_us()
        self._unplug_noted = False

    def _arm_unplug(self, unplug: UnplugParams | None, t0_us: float, *, lost_frames_on_edges: bool) -> None:
        """Armed once per world and device name: the replugged device is not unplugged again."""
        if unplug is not None and not self._fault.armed:
            self._fault.arm(
                t0_us + unplug.at_s * 1e6,
                t0_us + (unplug.at_s + unplug.for_s) * 1e6,
                lost_frames_on_edges=lost_frames_on_edges,
            )

    def _dead(self, true_us: float) -> bool:
        """Was this device object unplugged by that true time (its handle is stale for good)?"""
        return self._fault.kills(self._opened_us, true_us)

    def _unplugged_error(self) -> DeviceError:
        return DeviceError(
            f"{self._device_label} {self._name}: device unplugged (gone from the bus); "
            "close it and open it again"
        )

    def _check_present(self) -> None:
        """DeviceError once unplugged; what the host had not read yet is logged as lost."""
        if self._dead(self._world.now_us()):
            with self._lock:
                self._note_unplug_locked([])
            raise self._unplugged_error()

    def _on_unplug(self) -> None:
        """Timer thread, at the unplug instant: what the host has not read yet is lost."""
        with self._lock:
            if self._dead(self._world.now_us()):
                self._note_unplug_locked([])
