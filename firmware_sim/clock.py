"""The simulated world's true time: the host's monotonic clock, or a virtual one.

`RealClock` runs the sim in real time, so the daemon meets real deadlines. `VirtualClock`
(`clock=virtual` in a sim spec) is a discrete-event clock: time stands still while any
device holds it (a camera rendering a latched exposure, an event sensor generating a slice,
a device waiting for room in its buffer) and otherwise jumps to the earliest time some
device sleeps until. A rig on it runs as fast as the CPU and the host's reading allow, loses
nothing to its own slowness (a full buffer holds time instead of dropping data), and gives
the same data for the same config and seed however loaded the machine is.

Time starts at 0 and stays there until the world is started (`start`: the trigger box's
START, a free-running camera), so every device opened and started before the first pulse
starts at the same instant, whatever the host's timing.

A `Hold` is how a device thread takes part: while held, time does not move; `Hold.sleep_until`
lets go while asleep and takes the hold again, atomically, at the instant it is woken.
Sleeping without a hold (`SimClock.sleep_until`) waits for time to get there without stopping it.

The world's host clock (`host_clock`, what its devices stamp `host_time_ns` with) is the host's
monotonic clock on the real clock and `VirtualHostClock` on the virtual one: host and rig time
then advance together, as they do on hardware, whatever the machine's load.

A virtual clock may be shared with other processes over the simulated trigger cable
(`firmware_sim.cable`, a `ClockLink`): the lead's clock advances only when its followers are
idle too, to the earliest deadline of them all; a follower's clock never advances on its own,
it moves where the lead sends it and reports when nothing holds it there.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Literal, Protocol

from rigd.core.host_clock import MONOTONIC, HostClock

log = logging.getLogger(__name__)

ClockMode = Literal["real", "virtual"]
CLOCK_MODES: tuple[ClockMode, ...] = ("real", "virtual")

#: How often a sleeper looks at its stop event (wall seconds); time itself never polls.
_STOP_POLL_S = 0.05


class Hold(Protocol):
    """A device thread's claim on the present (a no-op on the real clock)."""

    def sleep_until(self, true_us: float, stop: threading.Event | None = None) -> bool:
        """Let go, sleep until `true_us`, hold again; False (not holding) if `stop` came first."""
        ...

    def release(self) -> None:
        """Let time go on (idempotent)."""
        ...


class SimClock(Protocol):
    mode: ClockMode

    def now_us(self) -> float: ...

    def sleep_until(self, true_us: float, stop: threading.Event | None = None) -> bool: ...

    def hold(self) -> Hold: ...

    def start(self) -> None: ...

    def call_at(self, true_us: float, fn: Callable[[], None], name: str) -> None: ...

    def wait(self, cond: threading.Condition, predicate: Callable[[], bool], timeout_s: float) -> bool: ...


class ClockLink(Protocol):
    """A virtual clock's share with other processes (`firmware_sim.cable`); every method is
    called with the clock's lock held, so it must only look at its own state and queue sends."""

    @property
    def leads(self) -> bool:
        """True on the lead (it advances the shared clock), False on a follower."""
        ...

    def others_idle(self) -> bool:
        """Lead: every follower has taken in all it was sent and holds nothing."""
        ...

    def others_deadline(self) -> float:
        """Lead: the earliest deadline some follower sleeps until (inf: none)."""
        ...

    def advanced(self, now_us: float) -> None:
        """Lead: the clock stands at `now_us`; send it to the followers that need it."""
        ...

    def settled(self, idle: bool, deadline_us: float) -> None:
        """Follower: report whether anything holds time here, and the earliest deadline."""
        ...

    def before_start(self) -> None:
        """Lead: wait (bounded) for the followers the clock must not start without."""
        ...


class _NoHold:
    def __init__(self, clock: RealClock) -> None:
        self._clock = clock

    def sleep_until(self, true_us: float, stop: threading.Event | None = None) -> bool:
        return self._clock.sleep_until(true_us, stop)

    def release(self) -> None:
        pass


class RealClock:
    """True time = the host's monotonic clock since the world was made."""

    mode: ClockMode = "real"

    def __init__(self) -> None:
        self._epoch_ns = time.monotonic_ns()

    @property
    def epoch_ns(self) -> int:
        """The monotonic clock's reading at true time 0."""
        return self._epoch_ns

    def adopt_epoch(self, epoch_ns: int) -> None:
        """Count true time from another process's epoch (one CLOCK_MONOTONIC per machine:
        a cable follower takes its lead's, so their true times agree)."""
        self._epoch_ns = int(epoch_ns)

    def now_us(self) -> float:
        return (time.monotonic_ns() - self._epoch_ns) / 1000.0

    def sleep_until(self, true_us: float, stop: threading.Event | None = None) -> bool:
        """Sleep until a true time; False if `stop` was set first."""
        while True:
            remaining = (true_us - self.now_us()) / 1e6
            if remaining <= 0:
                return True
            if stop is not None:
                if stop.wait(min(remaining, _STOP_POLL_S)):
                    return False
            else:
                time.sleep(min(remaining, _STOP_POLL_S))

    def hold(self) -> Hold:
        return _NoHold(self)

    def start(self) -> None:
        pass

    def call_at(self, true_us: float, fn: Callable[[], None], name: str) -> None:
        timer = threading.Timer(max(0.0, (true_us - self.now_us()) / 1e6), fn)
        timer.name = name
        timer.daemon = True
        timer.start()

    def wait(self, cond: threading.Condition, predicate: Callable[[], bool], timeout_s: float) -> bool:
        """Wait (holding `cond`) for `predicate`, at most `timeout_s` wall seconds."""
        return cond.wait_for(predicate, timeout=timeout_s)


class _VirtualHold:
    def __init__(self, clock: VirtualClock) -> None:
        self._clock = clock
        self._held = True

    def sleep_until(self, true_us: float, stop: threading.Event | None = None) -> bool:
        return self._clock._sleep(true_us, stop, self)

    def release(self) -> None:
        self._clock._release(self)

    def __del__(self) -> None:
        if self._held:  # a hold dropped without release would stop time for good
            log.error("virtual clock: a hold was dropped without release; releasing it")
            self._clock._release(self)


class VirtualClock:
    """Discrete-event time: see the module docstring."""

    mode: ClockMode = "virtual"

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._now = 0.0
        self._started = False
        self._holds = 0
        self._seq = itertools.count()
        #: (deadline, seq, hold or None) of every sleeper; entries of woken sleepers are stale.
        self._sleepers: list[tuple[float, int, _VirtualHold | None]] = []
        self._waiting: set[int] = set()
        self._link: ClockLink | None = None
        self.advances = 0

    def attach(self, link: ClockLink) -> None:
        """Share this clock with other processes (the simulated trigger cable); once only."""
        with self._cond:
            if self._link is not None:
                raise RuntimeError("virtual clock: already shared over a cable")
            self._link = link
            self._advance_locked()

    def update(self, change: Callable[[], None] | None = None, *, to_us: float | None = None) -> None:
        """Under the clock's lock: apply a cable's `change` to its own state, move a follower's
        time on to `to_us` (waking its sleepers due by then, holding), then advance or report."""
        with self._cond:
            if change is not None:
                change()
            if to_us is not None:
                if to_us > self._now:
                    self._now = to_us
                    self.advances += 1
                self._wake_due_locked()
            self._advance_locked()

    def now_us(self) -> float:
        with self._cond:
            return self._now

    def start(self) -> None:
        """Let time run (the trigger box started, or a free-running camera). A cable lead
        first waits for its followers (raising if they do not come); on a follower this does
        nothing: its time is the lead's."""
        link = self._link
        if link is not None:
            if not link.leads:
                return
            link.before_start()
        with self._cond:
            if not self._started:
                self._started = True
                log.info("virtual clock started")
                self._advance_locked()

    @property
    def started(self) -> bool:
        with self._cond:
            return self._started

    def hold(self) -> Hold:
        with self._cond:
            self._holds += 1
            if self._link is not None and not self._link.leads:
                self._advance_locked()  # a follower tells its lead it holds time now
        return _VirtualHold(self)

    def wait_sleepers(self, n: int, timeout_s: float = 10.0) -> bool:
        """Wait until `n` threads sleep on this clock (tests: a state to wait for, not a delay)."""
        with self._cond:
            return self._cond.wait_for(lambda: len(self._waiting) >= n, timeout=timeout_s)

    def sleep_until(self, true_us: float, stop: threading.Event | None = None) -> bool:
        return self._sleep(true_us, stop, None)

    def call_at(self, true_us: float, fn: Callable[[], None], name: str) -> None:
        """Run `fn` at `true_us`, with time held until it returns (it happens at that instant)."""
        hold = self.hold()

        def run() -> None:
            try:
                if hold.sleep_until(true_us):
                    fn()
            finally:
                hold.release()

        threading.Thread(target=run, name=name, daemon=True).start()

    def wait(self, cond: threading.Condition, predicate: Callable[[], bool], timeout_s: float) -> bool:
        """Wait (holding `cond`) for `predicate`, however long it takes: on virtual time a
        device waits for the host instead of giving data up."""
        while not cond.wait_for(predicate, timeout=_STOP_POLL_S):
            pass
        return True

    # -- internals -----------------------------------------------------------------------
    def _release(self, hold: _VirtualHold) -> None:
        with self._cond:
            if not hold._held:
                return
            hold._held = False
            self._holds -= 1
            self._advance_locked()

    def _sleep(self, true_us: float, stop: threading.Event | None, hold: _VirtualHold | None) -> bool:
        with self._cond:
            if stop is not None and stop.is_set():
                if hold is not None and hold._held:
                    hold._held = False
                    self._holds -= 1
                    self._advance_locked()
                return False
            if true_us <= self._now and (hold is None or hold._held):
                return True
            seq = next(self._seq)
            if hold is not None and hold._held:
                hold._held = False
                self._holds -= 1
            heapq.heappush(self._sleepers, (true_us, seq, hold))
            self._waiting.add(seq)
            self._cond.notify_all()
            self._advance_locked()
            while seq in self._waiting:
                if stop is not None and stop.is_set():
                    self._waiting.discard(seq)
                    return False
                self._cond.wait(_STOP_POLL_S if stop is not None else None)
            if hold is None:
                # Woken without a hold, this sleeper does not keep time here: the next deadline
                # may come at once (nothing else would move time on if it was alone).
                self._advance_locked()
            return True

    def _next_deadline_locked(self) -> float:
        """The earliest deadline a sleeper still waits for (inf: none)."""
        heap = self._sleepers
        while heap and heap[0][1] not in self._waiting:
            heapq.heappop(heap)  # a sleeper that left on its stop event
        return heap[0][0] if heap else math.inf

    def _wake_due_locked(self) -> None:
        """Wake every sleeper due by now; those with a hold hold time again."""
        heap = self._sleepers
        while heap and (heap[0][0] <= self._now or heap[0][1] not in self._waiting):
            _, seq, hold = heapq.heappop(heap)
            if seq not in self._waiting:
                continue
            self._waiting.discard(seq)
            if hold is not None:
                hold._held = True
                self._holds += 1
        self._cond.notify_all()

    def _advance_locked(self) -> None:
        """Jump to the earliest deadline when nothing holds time; wake those due, holding.

        Shared over a cable: a follower only reports (its lead moves it, `update`); the lead
        also waits for every follower to be idle and takes the earliest deadline of them all."""
        link = self._link
        if link is not None and not link.leads:
            link.settled(self._holds == 0, self._next_deadline_locked())
            return
        if not self._started or self._holds:
            return
        t = self._next_deadline_locked()
        if link is not None:
            if not link.others_idle():
                return
            t = min(t, link.others_deadline())
        if math.isinf(t):
            return
        if t > self._now:
            self._now = t
            self.advances += 1
        self._wake_due_locked()
        if link is not None:
            link.advanced(self._now)


def make_clock(mode: ClockMode) -> RealClock | VirtualClock:
    return VirtualClock() if mode == "virtual" else RealClock()


class VirtualHostClock:
    """Host time on a virtual world: `epoch_ns + round(virtual now_us * 1000)`.

    The epoch is the monotonic clock's reading when the world was made, so host times keep
    plausible magnitudes; past it they move only with virtual time. A device stamps data it
    hands to the host at the virtual instant it does so, as a host on hardware reads its clock
    when the data arrives, and the same take on a loaded or an idle machine gets the same host
    times, less the epoch."""

    def __init__(self, clock: VirtualClock, epoch_ns: int | None = None) -> None:
        self._clock = clock
        self._epoch_ns = time.monotonic_ns() if epoch_ns is None else int(epoch_ns)

    @property
    def epoch_ns(self) -> int:
        """Host time at virtual time 0."""
        return self._epoch_ns

    def adopt_epoch(self, epoch_ns: int) -> None:
        """Count from another process's epoch (a cable follower takes its lead's: their virtual
        times are one, so their host times agree too)."""
        self._epoch_ns = int(epoch_ns)

    def now_ns(self) -> int:
        return self._epoch_ns + round(self._clock.now_us() * 1000)

    def __repr__(self) -> str:
        return f"VirtualHostClock(epoch_ns={self._epoch_ns})"


def make_host_clock(clock: RealClock | VirtualClock) -> HostClock:
    """The host clock of a world on `clock` (see the module docstring)."""
    return VirtualHostClock(clock) if isinstance(clock, VirtualClock) else MONOTONIC
