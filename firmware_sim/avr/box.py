"""The trigger-box firmware as a sim-world device: the AVR image a lab flashes, run cycle by
cycle under simavr (`firmware_sim.avr.harness`), driving the world's trigger wire.

`avr://WORLD/trigger?elf=PATH&mcu=atmega328p` opens it with the unmodified host driver
(`drivers.serial_trigger`) on the harness's pty. The sim cameras and event sensors of the
world see the firmware's own edges: every change of the trigger pin becomes an `Edge` on the
world's wire at the time of its Timer1 tick (the cycle rounded to the 8-cycle tick, which
removes the 0-4 cycles an instruction boundary adds in the simulator).

Time. On the real clock the firmware runs in step with the host's clock, a couple of
milliseconds ahead, and its edges fire when the world's time reaches them. On the virtual
clock the world's time *is* the firmware's cycle count while a run is on: from the moment the
firmware schedules its first edge (START) until its last edge is out, world time and AVR time
advance together (`world_us = tick / 2 + offset`). The firmware runs `LEAD_US` ahead of the
world, or `HOST_LEAD_US` while the host has sent it bytes (a reply never waits for a slow
device); its edges are held back until the world reaches them, and the world can never pass
the firmware. While the firmware has no
edge scheduled it is "quiet" and its time stands still between host commands (the harness's
FREE): the host's speed never reaches the firmware's clock, so a take is the same twice.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from pathlib import Path

from firmware_sim.avr.harness import AvrHarness
from firmware_sim.avr.harness import Edge as PinEdge
from firmware_sim.clock import Hold
from firmware_sim.world import DeviceClock, Edge, SimWorld

log = logging.getLogger(__name__)

FREQ_HZ = 16_000_000
CYCLES_PER_US = FREQ_HZ // 1_000_000
#: Timer1 runs at F_CPU / 8: the firmware's edges fall on these.
CYCLES_PER_TICK = 8
#: How far (virtual microseconds) the firmware runs ahead of the world on the virtual clock:
#: its pulse records and END reach the host about when the world has the edges, as a real box's
#: would (the capture's stop waits a wall-clock backlog after END, not a virtual one).
LEAD_US = 2_000
#: How far it may run ahead while the host has sent it something: a reply never waits for a
#: slow world (the driver's reply timeout is wall-clock).
HOST_LEAD_US = 100_000
#: How often (wall seconds) the firmware, held back by the world, looks for host bytes.
HOST_POLL_S = 0.01
#: How far ahead of the host's clock the firmware runs on the real clock.
REAL_LEAD_US = 2_000
TRIGGER_PIN = "TRIG"


def edge_tick(cycle: int) -> int:
    """The Timer1 tick an output-compare edge seen at `cycle` belongs to: the simulator reports
    it at the end of the instruction under way (0-4 cycles late) and the firmware's ticks start
    one cycle after a multiple of 8 (firmware/trigger_box/pulse.c)."""
    return (cycle + 3) // CYCLES_PER_TICK


class AvrTriggerBox:
    """The firmware under simavr, its pin on the world's trigger wire, its UART on a pty."""

    def __init__(self, world: SimWorld, elf: Path, *, mcu: str = "atmega328p") -> None:
        self.world = world
        # The host speaks in lines: FREE hands the firmware each when it is idle, so the
        # host's timing never reaches the firmware's clock (docs/decisions/0027).
        self.harness = AvrHarness(elf, mcu=mcu, clock="control", free_lines=True)
        self.port_path = self.harness.port_path
        #: (cycle, level) of every trigger-pin change, for tests.
        self.edges: list[tuple[int, int]] = []
        #: Rising edges fired on the wire over all runs.
        self.pulses_fired = 0
        #: Why the device thread stopped, if it failed.
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._closed = False
        self._offset_us = 0.0  # world_us = tick / 2 + offset
        self._run_pulses = 0
        self._cond = threading.Condition()
        self._pending: deque[PinEdge] = deque()
        self._avr_cycle = 0
        self._quiet = True
        self._segment: Hold | None = None
        target = self._drive_virtual if world.virtual else self._drive_real
        self._driver = threading.Thread(target=self._guard, args=(target,), name=f"avr-box-{world.name}")
        self._firer: threading.Thread | None = None
        if world.virtual:
            self._firer = threading.Thread(
                target=self._guard, args=(self._fire_virtual,), name=f"avr-wire-{world.name}", daemon=True
            )
            self._firer.start()
        else:
            self._link_clock(0, world.now_us())
        self._driver.daemon = True
        self._driver.start()
        log.info("AVR trigger box %s (%s) for world %r on %s", elf.name, mcu, world.name, self.port_path)

    @property
    def closed(self) -> bool:
        return self._closed

    # ------------------------------------------------------------------ time mapping
    def _link_clock(self, cycle: int, world_us: float) -> None:
        """From now on, AVR `cycle` is world time `world_us`; the truth clock says so too."""
        # Whole microseconds: edges fall on even ticks (2 * b_k), so their world times are whole
        # microseconds too, as the Python box fires them.
        self._offset_us = world_us - edge_tick(cycle) // 2
        self.world.register_clock("trigger", DeviceClock(offset_us=-self._offset_us))

    def _world_us(self, cycle: int) -> float:
        return edge_tick(cycle) / 2 + self._offset_us

    def _cycle_at(self, world_us: float) -> int:
        return int((world_us - self._offset_us) * CYCLES_PER_US)

    def _fire(self, edge: PinEdge) -> None:
        true_us = self._world_us(edge.cycle)
        rising = edge.value == 1
        index = self._run_pulses if rising else self._run_pulses - 1
        if rising:
            self._run_pulses += 1
            self.pulses_fired += 1
        self.world.wire.fire(Edge(rising=rising, true_us=true_us, pulse_index=index))
        if rising:
            self.world.truth.add_pulse(index, edge_tick(edge.cycle) // 2, true_us, True)

    def _note(self, edges: list[PinEdge]) -> list[PinEdge]:
        trig = [e for e in edges if e.pin == TRIGGER_PIN]
        self.edges.extend((e.cycle, e.value) for e in trig)
        return trig

    # ------------------------------------------------------------------ threads
    def _guard(self, body: Callable[[], None]) -> None:
        try:
            body()
        except BaseException as exc:
            if self._stop.is_set():
                log.debug("AVR trigger box %s: %s ends on close: %s", self.port_path, body, exc)
                return
            self.error = exc
            log.exception("AVR trigger box %s failed; closing its pty", self.port_path)
            self._stop.set()
            with self._cond:
                self._cond.notify_all()
            self.harness.close()
            raise

    def _drive_real(self) -> None:
        """Keep the firmware REAL_LEAD_US ahead of the host's clock; fire edges on time."""
        cycle = 0
        while not self._stop.is_set():
            now = self.world.now_us()
            step = self.harness.run_until(max(cycle, self._cycle_at(now + REAL_LEAD_US)))
            cycle = step.cycle
            for edge in self._note(step.edges):
                if not self.world.sleep_until(self._world_us(edge.cycle), self._stop):
                    return
                self._fire(edge)
            self.world.sleep_until(self._world_us(cycle) - REAL_LEAD_US / 2, self._stop)

    def _drive_virtual(self) -> None:
        """Quiet firmware: FREE (its time stands still between host commands). Scheduled
        firmware: link its cycles to the world's time and advance up to LEAD_US ahead."""
        clock = self.world.clock
        while not self._stop.is_set():
            step = self.harness.free()
            if self._note(step.edges):  # a quiet firmware schedules no edge, so it makes none
                raise RuntimeError(f"AVR trigger box {self.port_path}: edges while quiet: {step.edges[:4]}")
            if self._stop.is_set():
                return
            if step.quiet:
                continue
            cycle = step.cycle
            with self._cond:
                self._cond.wait_for(lambda: self._segment is None or self._stop.is_set())
                if self._stop.is_set():
                    return
                hold = clock.hold()  # the world waits here until the firer has the first edge
                self._link_clock(cycle, clock.now_us())
                self._avr_cycle = cycle
                self._quiet = False
                self._run_pulses = 0
                self._segment = hold
                self._cond.notify_all()
            clock.start()  # a virtual world's time runs from the first START
            boost = 0  # cycle up to which the firmware may run to answer the host
            while not self._stop.is_set():

                def horizon(boost: int = boost) -> int:
                    return max(self._cycle_at(clock.now_us() + LEAD_US), boost)

                with self._cond:
                    self._cond.wait_for(
                        lambda: self._stop.is_set() or self._avr_cycle < horizon(), timeout=HOST_POLL_S
                    )
                    # At the horizon this runs no cycle: it asks whether host bytes wait.
                    target = max(horizon(), self._avr_cycle)
                step = self.harness.run_until(target)
                if step.host_waiting:
                    boost = step.cycle + HOST_LEAD_US * CYCLES_PER_US
                trig = self._note(step.edges)
                with self._cond:
                    self._pending.extend(trig)
                    self._avr_cycle = step.cycle
                    self._quiet = step.quiet
                    self._cond.notify_all()
                if step.quiet:
                    break

    def _fire_virtual(self) -> None:
        """Hold the world at the firmware's time, and fire each edge when the world gets there."""
        clock = self.world.clock
        while not self._stop.is_set():
            with self._cond:
                self._cond.wait_for(lambda: self._segment is not None or self._stop.is_set())
                hold = self._segment
            if hold is None:
                return
            try:
                while not self._stop.is_set():
                    with self._cond:
                        if self._pending:
                            target = self._world_us(self._pending[0].cycle)
                        elif self._quiet:
                            break  # the run is over and its last edge is out
                        else:
                            target = self._world_us(self._avr_cycle)
                    if target > clock.now_us() and not hold.sleep_until(target, self._stop):
                        return
                    due: list[PinEdge] = []
                    with self._cond:
                        now = clock.now_us()
                        while self._pending and self._world_us(self._pending[0].cycle) <= now:
                            due.append(self._pending.popleft())
                        if not due and not self._quiet and self._world_us(self._avr_cycle) <= now:
                            # The world has caught up with the firmware: wait for it, holding time.
                            self._cond.wait(0.05)
                    for edge in due:
                        self._fire(edge)
            finally:
                hold.release()
                with self._cond:
                    self._segment = None
                    self._cond.notify_all()

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        """Stop the threads and the simulator; the pty goes with it. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        self.harness.close()
        self._driver.join(10)
        if self._firer is not None:
            self._firer.join(10)
        log.info("AVR trigger box on %s closed (%d pulses fired)", self.port_path, self.pulses_fired)
