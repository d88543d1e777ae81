"""Pulses fired on a sim world's trigger wire, as the trigger box fires them."""

from __future__ import annotations

from firmware_sim.world import Edge, SimWorld


def fire_pulses(world: SimWorld, n: int, rate_hz: float = 100.0, width_us: float = 500.0) -> list[float]:
    """Fire n pulses on the wire in real time (rising, then falling after width_us).

    Returns the true times of the rising edges.
    """
    period = 1e6 / rate_hz
    t_first = world.now_us() + 2000.0
    times = []
    for i in range(n):
        t = t_first + i * period
        world.sleep_until(t)
        world.wire.fire(Edge(True, t, i))
        world.sleep_until(t + width_us)
        world.wire.fire(Edge(False, t + width_us, i))
        times.append(t)
    return times
