"""The coarse placement needs host time that runs at one rate with rig time.

`host_to_rig_map` is a line through the pulse records' arrival times, and the shift among the
pulse train's feasible ones is chosen by host time. On a simulated world's virtual clock, the
machine's monotonic clock has no fixed rate to rig time (virtual time jumps while the world is
idle and stands still while a device holds it), so stamping with it puts a kink into the host
timeline. The world's own host clock (epoch + virtual time) has none.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from rigd.sync import DeviceObservations, PulseLog, host_to_rig_map, match_device

RATE = 30.0
PERIOD = 1e6 / RATE
N = 90
#: The camera saw pulses from this one on (it came back from a replug), so the pulse train
#: alone cannot place it: host time must choose among the feasible shifts.
FIRST_SEEN = 30
EPOCH_NS = 5_000_000_000_000
RECORD_LATENCY_US = 500.0
FRAME_LATENCY_US = 6_000.0


def _world_host(rig_us: NDArray[np.float64]) -> NDArray[np.float64]:
    """Host time on the world's clock: one rate with rig time."""
    return rig_us


def _wall_host(rig_us: NDArray[np.float64]) -> NDArray[np.float64]:
    """A monotonic clock read on a virtual world: one rate for the first 2 s of rig time, then
    time the world ran 2.5 times faster than the machine (it was idle: time jumped)."""
    kink = 2_000_000.0
    return np.where(rig_us < kink, rig_us, kink + (rig_us - kink) * 0.4)


def _match(to_host: Callable[[NDArray[np.float64]], NDArray[np.float64]]) -> NDArray[np.int64]:
    k = np.arange(N, dtype=np.int64)
    t_us = (np.rint(k * PERIOD) + 1_000_000).astype(np.int64)
    seen = k[FIRST_SEEN:]
    device_us = t_us[seen] - 4_321_000  # the camera's own clock (restarted: far from rig time)
    records_ns = (EPOCH_NS + to_host(t_us + RECORD_LATENCY_US) * 1000).astype(np.int64)
    frames_ns = (EPOCH_NS + to_host(t_us[seen] + FRAME_LATENCY_US) * 1000).astype(np.int64)
    pulses = PulseLog.from_records(k, t_us, records_ns, N)
    obs = DeviceObservations("cam2", "rgb_camera", device_us, frames_ns)
    match = match_device(obs, pulses, PERIOD, host_to_rig_map(pulses))
    return match.pulse_index


def test_host_times_on_the_world_clock_place_a_late_device_on_its_pulses() -> None:
    assert _match(_world_host).tolist() == list(range(FIRST_SEEN, N))


def test_host_times_on_a_clock_whose_rate_changes_mid_take_place_it_a_period_off() -> None:
    """What stamping with the machine's clock on virtual time did: the same observations, tied
    one pulse early (the post-replug symptom of a loaded machine)."""
    index = _match(_wall_host)
    assert index.tolist() != list(range(FIRST_SEEN, N))
    assert (index[index >= 0] - np.arange(FIRST_SEEN, N)[index >= 0] <= -1).all()
