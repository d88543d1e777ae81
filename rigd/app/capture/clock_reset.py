"""Re-tying a device that came back from a replug with its clock restarted.

Most cameras and event sensors reset their timestamp counter when they power up, so a device
that was unplugged mid-take returns counting from zero. One clock map per device cannot span
that, and the take's per-device times must stay monotonic. The trigger pulses fix it: the
device's observations before the gap give its clock map (offset and drift), and a few
trigger observations after it, matched to box pulses, tell where the new counter sits on the
old one. Every later time of that device is shifted by that offset before it is written, so
the take holds one continuous device clock and the usual single fit covers the whole take.
Until the offset is known (a handful of pulses) the device's data is held back, not written;
if it cannot be tied (too few observations, no pulse match) the device is written off as
before and what was held is counted as lost.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import ClassVar, Generic, Protocol, TypeVar

import numpy as np

from rigd.core.events import EventPacket
from rigd.core.frames import Frame
from rigd.core.kinds import SensorKind
from rigd.sync import DeviceObservations, PulseLog, host_to_rig_map, match_device

log = logging.getLogger(__name__)

ItemT = TypeVar("ItemT", Frame, EventPacket)

#: Trigger observations after the replug needed to place the new counter on the old clock.
MIN_OBSERVATIONS = 5
#: Give up (write the device off) when this many observations after the replug do not tie,
MAX_OBSERVATIONS = 60
#: or when its data has been held this long (a sensor whose trigger input is not wired).
MAX_HOLD_S = 5.0


@dataclass(frozen=True, slots=True)
class Offset:
    """new device time + `us` = the same instant on the device's clock before the reset."""

    us: int
    n: int
    """Post-replug observations it rests on."""
    spread_us: float
    """Largest disagreement among them (jitter plus drift extrapolation over the gap)."""


class HeldItems(Protocol[ItemT]):
    """What re-tying asks of a device kind's items (`reading.Reading` is one)."""

    kind: ClassVar[SensorKind]

    def count(self, item: ItemT) -> int: ...
    def observations(self, item: ItemT) -> list[int]: ...
    def shifted(self, item: ItemT, us: int) -> ItemT: ...


@dataclass(slots=True)
class ClockReset(Generic[ItemT]):
    """One device between its return with a restarted clock and the end of the take."""

    name: str
    items: HeldItems[ItemT]
    """How the device's items are counted, observed and shifted (its kind's reading part)."""
    t_before: int
    """The last device time before the gap, on the old clock."""
    offset: Offset | None = None
    held: list[ItemT] = field(default_factory=list)
    """Frames or packets delivered before the offset was known, in order."""
    post_t: list[int] = field(default_factory=list)
    post_host: list[int] = field(default_factory=list)

    @property
    def kind(self) -> SensorKind:
        return self.items.kind

    def hold(self, item: ItemT) -> None:
        self.held.append(item)
        seen = self.items.observations(item)
        self.post_t.extend(seen)
        self.post_host.extend([item.host_time_ns] * len(seen))

    def held_for_s(self) -> float:
        """Host time from the first held item to the last."""
        if len(self.held) < 2:
            return 0.0
        return (self.held[-1].host_time_ns - self.held[0].host_time_ns) / 1e9

    def held_count(self) -> int:
        """Frames or events held back (what is lost if the device cannot be tied)."""
        return sum(self.items.count(item) for item in self.held)

    def shift(self, item: ItemT) -> ItemT:
        assert self.offset is not None
        return self.items.shifted(item, self.offset.us)

    def release(self) -> list[ItemT]:
        """The held items, shifted onto the old clock; the hold is emptied."""
        out = [self.shift(item) for item in self.held]
        self.held.clear()
        return out


def estimate_offset(
    reset: ClockReset,
    pre_t: np.ndarray,
    pre_host: np.ndarray,
    pulses: PulseLog,
    period_us: float,
) -> Offset | None:
    """Where the restarted counter sits on the old clock, or None while it cannot be told.

    The pre-gap observations are matched and fitted as the sync engine does at the end of
    the take; the post-replug ones are matched to pulses on their own (host times and the
    pulse train's spacing); each matched pulse's rig time, taken back through the old fit,
    is the old-clock time of that observation.
    """
    n_post = len(reset.post_t)
    if n_post < MIN_OBSERVATIONS or pre_t.size < 3 or pulses.t_us.size < 3:
        return None
    host_map = host_to_rig_map(pulses)
    pre = DeviceObservations(reset.name, reset.kind, pre_t, pre_host)
    before = match_device(pre, pulses, period_us, host_map)
    post_t = np.asarray(reset.post_t, np.int64)
    after = match_device(
        DeviceObservations(reset.name, reset.kind, post_t, np.asarray(reset.post_host, np.int64)),
        pulses,
        period_us,
        host_map,
    )
    if before.fit is None:
        return None
    ok = after.pulse_index >= 0
    if ok.sum() < MIN_OBSERVATIONS - 2:
        return None
    rig_of = dict(zip(pulses.index.tolist(), pulses.t_us.tolist(), strict=True))
    rig = np.asarray([rig_of[int(k)] for k in after.pulse_index[ok]], np.int64)
    old = before.fit.map.to_device(rig)
    offsets = (old - post_t[ok]).astype(np.float64)
    k = float(np.median(offsets))
    spread = float(np.abs(offsets - k).max())
    if spread > period_us / 4:
        log.warning("%s: offsets after the clock reset disagree by %.0f us; not tied yet", reset.name, spread)
        return None
    return Offset(round(k), int(ok.sum()), spread)
