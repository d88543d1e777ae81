"""Host time: the clock a device stamps what it hands to the host with (`host_time_ns`).

On hardware that is the host's monotonic clock (`MONOTONIC`). A simulated world owns its host
clock: on virtual time the devices' data and the box's pulse records reach the "host" at
virtual instants, so their host times must be read off the world's clock, or the sync engine's
coarse placement (a line through pulse arrival times) and every "how old is this item" would
mix two clocks whose rate to each other changes with the machine's load
(docs/decisions/0038-host-time-belongs-to-the-world.md).

Whoever compares an item's host time with "now" asks the clock the item was stamped with: a
capture takes it from its trigger (`drivers.base.Device.host_clock`).
"""

from __future__ import annotations

import time
from typing import Protocol


class HostClock(Protocol):
    """Integer nanoseconds on one monotonic host timeline."""

    def now_ns(self) -> int: ...


class MonotonicClock:
    """The host's `time.monotonic_ns`: the host clock of real hardware."""

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def __repr__(self) -> str:
        return "MONOTONIC"


#: The default host clock of every device.
MONOTONIC: HostClock = MonotonicClock()
