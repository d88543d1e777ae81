"""The contract every `Trigger` backend runs; subclass it and provide a `trigger` fixture (an
opened trigger source whose pulses nobody else reads)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.base import Capability, Trigger
from rigd.core.devices import PulseBatch
from rigd.core.errors import ConfigError, DeviceError
from rigd.core.settings import TriggerSettings

RATE_HZ = 500.0
WIDTH_US = 200
PERIOD_US = 1e6 / RATE_HZ


def collect(trigger: Trigger, n: int, timeout_s: float = 5.0) -> PulseBatch:
    """Read pulse batches until n records arrived (or the deadline passed)."""
    parts: list[PulseBatch] = []
    deadline = time.monotonic() + timeout_s
    while sum(len(p) for p in parts) < n and time.monotonic() < deadline:
        parts.append(trigger.read_pulses(0.05))
    return PulseBatch(
        np.concatenate([p.index for p in parts]) if parts else np.empty(0, np.int64),
        np.concatenate([p.t_us for p in parts]) if parts else np.empty(0, np.int64),
        np.concatenate([p.host_time_ns for p in parts]) if parts else np.empty(0, np.int64),
    )


def wait_stopped(trigger: Trigger, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while trigger.is_running():
        assert time.monotonic() < deadline, "trigger still running past its pulse count"
        time.sleep(0.01)


class TriggerContract:
    """Behaviour the daemon relies on, whatever box sits behind the interface."""

    def _configured(self, trigger: Trigger) -> Trigger:
        trigger.configure(TriggerSettings(rate_hz=RATE_HZ, pulse_width_us=WIDTH_US))
        return trigger

    def test_info_and_kind(self, trigger: Trigger) -> None:
        assert trigger.kind == "trigger"
        assert trigger.info.kind == "trigger"
        assert trigger.info.spec

    def test_capabilities(self, trigger: Trigger) -> None:
        caps = trigger.capabilities
        assert isinstance(caps, frozenset)
        assert all(isinstance(c, Capability) for c in caps)
        assert Capability.PULSE_TIMESTAMPS in caps, "the rig timebase needs pulse timestamps"
        assert trigger.required_capabilities(TriggerSettings()) <= caps
        counted = trigger.required_capabilities(TriggerSettings(), n_pulses=10)
        assert Capability.PULSE_COUNT in counted
        if Capability.PULSE_COUNT not in caps:
            with pytest.raises(ConfigError, match="pulse_count"):
                trigger.start(10)

    def test_configure_rejects_width_not_shorter_than_period(self, trigger: Trigger) -> None:
        with pytest.raises(ConfigError):
            trigger.configure(TriggerSettings(rate_hz=1000.0, pulse_width_us=1000))
        with pytest.raises(ConfigError):
            trigger.start(0)

    def test_start_n_emits_exactly_n_at_the_period(self, trigger: Trigger) -> None:
        if Capability.PULSE_COUNT not in trigger.capabilities:
            pytest.skip("backend cannot emit an exact pulse count")
        self._configured(trigger).arm()
        assert trigger.pulse_count() == 0
        before = trigger.clock_us()
        t0 = trigger.start(20)
        assert before <= t0 <= before + 1_000_000
        batch = collect(trigger, 20)
        wait_stopped(trigger)
        assert trigger.pulse_count() == 20
        assert batch.index.dtype == np.int64
        assert batch.t_us.dtype == np.int64
        assert batch.index.tolist() == list(range(20))
        assert batch.t_us[0] >= t0
        assert np.diff(batch.t_us) == pytest.approx(PERIOD_US, abs=1.0)
        assert (np.diff(batch.host_time_ns) >= 0).all()
        assert len(trigger.read_pulses(0.05)) == 0  # nothing more after the count
        assert trigger.stop() == 20

    def test_stop_returns_count_and_every_pulse_is_reported(self, trigger: Trigger) -> None:
        self._configured(trigger).arm()
        trigger.start()
        assert trigger.is_running()
        first = collect(trigger, 5)
        assert len(first) >= 5
        count = trigger.stop()
        assert not trigger.is_running()
        assert count >= len(first)
        rest = collect(trigger, count - len(first), timeout_s=1.0)
        indices = np.concatenate([first.index, rest.index])
        times = np.concatenate([first.t_us, rest.t_us])
        assert indices.tolist() == list(range(count))
        assert (np.diff(times) > 0).all()
        assert trigger.pulse_count() == count

    def test_arm_resets_the_counter(self, trigger: Trigger) -> None:
        self._configured(trigger).arm()
        trigger.start(3)
        collect(trigger, 3)
        wait_stopped(trigger)
        trigger.arm()
        assert trigger.pulse_count() == 0
        trigger.start(2)
        assert collect(trigger, 2).index.tolist() == [0, 1]

    def test_read_pulses_times_out_empty(self, trigger: Trigger) -> None:
        t = time.monotonic()
        batch = trigger.read_pulses(0.1)
        assert len(batch) == 0
        assert time.monotonic() - t < 1.0

    def test_clock_advances_in_microseconds(self, trigger: Trigger) -> None:
        a = trigger.clock_us()
        time.sleep(0.1)
        b = trigger.clock_us()
        assert 80_000 <= b - a <= 600_000

    def test_close_while_pulsing_is_clean_and_idempotent(self, trigger: Trigger) -> None:
        self._configured(trigger).arm()
        trigger.start()
        collect(trigger, 2)
        trigger.close()  # stops the run first
        assert trigger.closed
        trigger.close()

    def test_a_closed_trigger_says_so_naming_itself(self, trigger: Trigger) -> None:
        trigger.close()
        for call in (trigger.arm, trigger.start, trigger.pulse_count, lambda: trigger.read_pulses(0.0)):
            with pytest.raises(DeviceError, match="closed") as err:
                call()
            assert trigger.label in str(err.value)
