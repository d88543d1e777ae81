"""The trigger of a host that has no box: the coordinator's pulse records, fetched over the network.

On a multi-host rig (docs/multi-host.md) one host owns the trigger box; the hardware line reaches
every device, but the box's *records* (pulse index and box time, the rig timebase) reach only
that host. A follower host's take needs them to map its devices to rig time exactly as a
one-host take does, so its session runs with a `RemoteTrigger`: a `Trigger` whose records come
from a `PulseFeed` (the coordinator's `pulses` command). Starting and stopping the box is the
coordinator's; this side only follows, and says so in `link_stats` (records fetched, requests
that failed) so a flaky network is visible in the take.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from drivers.base import Capability, Trigger
from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.errors import DeviceError
from rigd.core.host_clock import MONOTONIC, HostClock
from rigd.core.settings import TriggerSettings

log = logging.getLogger(__name__)

#: How long the stop waits for the coordinator to say how many pulses its box emitted.
STOP_WAIT_S = 30.0
#: A feed that fails for this long (wall seconds) is a lost coordinator: reads raise.
FEED_LOST_S = 10.0
#: How long the best (shortest round trip) clock offset sample stays the one used: host clocks
#: drift apart by up to ~100 ppm, 3 ms in 30 s.
OFFSET_REFRESH_S = 30.0
#: Pause between two fetches that brought nothing (the box pulses at tens of Hz).
_POLL_S = 0.05


class FeedDownError(DeviceError):
    """The coordinator could not be asked (a timeout, a refusal): retried until `FEED_LOST_S`."""


@dataclass(frozen=True, slots=True)
class FeedState:
    """One answer of the coordinator: records from `since` on, and where its box stands."""

    index: NDArray[np.int64]
    t_us: NDArray[np.int64]
    running: bool
    """The box is pulsing (or about to: armed and started)."""
    emitted: int | None
    """Pulses the box emitted, once it has stopped; None while it runs."""
    clock_us: int
    """The box clock when the coordinator answered (its last record's time if it cannot ask)."""
    host_ns: NDArray[np.int64] | None = None
    """When each record reached the coordinator, on its host clock (its trigger's)."""
    now_ns: int | None = None
    """The coordinator's host clock when it answered (None: no trigger open to read it from)."""


class PulseFeed(Protocol):
    """Where a follower's pulse records come from (`rigd.app.service.host_links.CoordinatorFeed`)."""

    name: str
    """The coordinator, as messages name it (`host A (tcp://...)`)."""

    def fetch(self, since: int) -> FeedState:
        """Records with index >= `since`; DeviceError when the coordinator cannot be asked."""
        ...


class RemoteTrigger(Trigger):
    """A follower host's trigger: reads the coordinator's records, never drives the box."""

    follows = True

    def __init__(self, feed: PulseFeed, *, spec: str, host_clock: HostClock = MONOTONIC) -> None:
        super().__init__()
        self._feed = feed
        self.host_clock = host_clock
        self._info = DeviceInfo(
            kind="trigger", spec=spec, model="remote pulse feed", facts={"from": feed.name}
        )
        self._capabilities = frozenset({Capability.PULSE_TIMESTAMPS, Capability.PULSE_COUNT})
        self._label = f"trigger of {feed.name}"
        self._lock = threading.Lock()
        self._reading = threading.Lock()
        """Only the reading thread takes records; the stop and the watchdog's probes only look."""
        self._next = 0
        self._running = False
        self._emitted: int | None = None
        self._box_us = 0
        self._stats = {"lines": 0, "records": 0, "feed_errors": 0}
        self._failing_since: float | None = None
        self._lost: str | None = None
        self._offset_ns: int | None = None
        self._offset_rtt = 0
        self._offset_at = 0

    # -- what the session calls ------------------------------------------------------------
    def _do_configure(self, settings: TriggerSettings) -> None:
        """The box's settings are the coordinator's; the same config gives the same ones."""

    def _do_arm(self) -> None:
        with self._lock:
            self._next = 0
            self._emitted = None

    def _do_start(self, n_pulses: int | None) -> int:
        """Nothing to start here: the coordinator starts the box once every host is armed."""
        with self._lock:
            self._running = True
            return self._box_us

    def _do_stop(self) -> int:
        """The pulses the coordinator's box emitted: asked until it has stopped (it stops the box
        before it tells the hosts to stop), at most `STOP_WAIT_S`; after that, the records seen."""
        with self._lock:
            if not self._running:
                return self._emitted if self._emitted is not None else self._next
        deadline = time.monotonic() + (0.0 if self._lost else STOP_WAIT_S)
        while True:
            try:
                state = self._fetch()
            except DeviceError as exc:
                log.warning("%s: cannot learn how many pulses the box emitted yet: %s", self.label, exc)
                state = None
            if state is not None and state.emitted is not None:
                emitted = state.emitted
                break
            if time.monotonic() >= deadline:
                emitted = self._next
                log.error(
                    "%s: the box had not stopped %.0f s after this host's stop; the take keeps the "
                    "%d pulse record(s) fetched",
                    self.label,
                    STOP_WAIT_S,
                    emitted,
                )
                break
            time.sleep(_POLL_S)
        with self._lock:
            self._running = False
            self._emitted = emitted
        return emitted

    def _is_running(self) -> bool:
        with self._lock:
            return self._running

    def _read_pulses(self, timeout_s: float) -> PulseBatch:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                with self._reading:
                    state = self._fetch(consume=True)
            except FeedDownError as exc:
                since = self._failing_since
                if since is not None and time.monotonic() - since > FEED_LOST_S and self._lost is None:
                    self._lost = f"{self._feed.name} has not answered for {FEED_LOST_S:g} s ({exc})"
                    log.error("%s: %s", self.label, self._lost)
                state = None
            if state is not None and len(state.index):
                return PulseBatch(state.index, state.t_us, self._host_times(state))
            if time.monotonic() >= deadline:
                return PulseBatch.empty()
            time.sleep(min(_POLL_S, max(0.0, deadline - time.monotonic())))

    def _pulse_count(self) -> int:
        state = self._fetch_quietly()
        if state is not None and state.emitted is not None:
            return state.emitted
        with self._lock:
            return self._next

    def _clock_us(self) -> int:
        self._fetch_quietly()
        with self._lock:
            return self._box_us

    def _stop_for_close(self) -> None:
        with self._lock:
            self._running = False

    def link_lost(self) -> str | None:
        return self._lost

    def link_stats(self) -> dict[str, int]:
        with self._lock:
            return dict(self._stats)

    def use_host_clock(self, clock: HostClock) -> None:
        """Put the records on `clock`: this host's devices' (a simulated world's on virtual time),
        which the session learns only once they are open; before the first fetch. The same clock
        again keeps the offset already measured (the real clock: nothing changes)."""
        with self._lock:
            if clock is self.host_clock:
                return
            self.host_clock = clock
            self._offset_ns = None

    # -- the feed ----------------------------------------------------------------------------
    def _host_times(self, state: FeedState) -> NDArray[np.int64]:
        """When each record would have reached this host had the box been cabled here: the
        coordinator's arrival times on this host's clock (`host_clock`, the one this host's
        devices stamp with). The sync engine's coarse map (host time -> rig time) needs them as
        a local box would give them; an arrival time here would lag by the network and the
        polling."""
        with self._lock:
            offset = self._offset_ns
        if state.host_ns is None or offset is None:
            return np.full(len(state.index), self.host_clock.now_ns(), np.int64)
        return state.host_ns - np.int64(offset)

    def _note_offset(self, t0: int, t1: int, state: FeedState) -> None:
        """Cristian's estimate of (coordinator host clock - this host clock) from one request:
        the one with the shortest round trip in the last `OFFSET_REFRESH_S` wins (error <=
        rtt / 2). Both sides read the clock their records are stamped with."""
        if state.now_ns is None:
            return
        rtt = t1 - t0
        offset = state.now_ns - (t0 + t1) // 2
        with self._lock:
            stale = t1 - self._offset_at > OFFSET_REFRESH_S * 1e9
            if self._offset_ns is None or stale or rtt <= self._offset_rtt:
                self._offset_ns, self._offset_rtt, self._offset_at = offset, rtt, t1
                self._stats["clock_rtt_us"] = rtt // 1000

    def _fetch(self, *, consume: bool = False) -> FeedState:
        """Ask the coordinator; only a consuming fetch (the reading thread's) moves on."""
        with self._lock:
            since = self._next
        try:
            clock = self.host_clock
            t0 = clock.now_ns()
            state = self._feed.fetch(since)
            self._note_offset(t0, clock.now_ns(), state)
        except DeviceError as exc:
            with self._lock:
                self._stats["feed_errors"] += 1
                if self._failing_since is None:
                    self._failing_since = time.monotonic()
            raise FeedDownError(str(exc)) from exc
        n = len(state.index)
        if n and (int(state.index[0]) != since or np.any(np.diff(state.index) != 1)):
            raise DeviceError(
                f"{self.label}: records from {int(state.index[0])} answered a request from {since} "
                "(the coordinator's records must come in order, without gaps)"
            )
        with self._lock:
            self._failing_since = None
            self._stats["lines"] += 1
            if consume:
                self._stats["records"] += n
                self._next = since + n
            self._box_us = max(self._box_us, state.clock_us)
            if state.emitted is not None:
                self._emitted = state.emitted
        return state

    def _fetch_quietly(self) -> FeedState | None:
        """For the watchdog's probes: a failed ask is counted, and the reads say when it is lost."""
        try:
            return self._fetch()
        except DeviceError as exc:
            log.warning("%s: %s", self.label, exc)
            return None
