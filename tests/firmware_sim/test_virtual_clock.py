"""The virtual clock: discrete-event time that holds still while devices work, and a sim rig
on it that gives the same take twice."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.registry import open_device
from firmware_sim.clock import VirtualClock, VirtualHostClock
from firmware_sim.world import SimWorld, get_world, reset_world
from rigd.app.capture import run_capture
from rigd.app.config import default_sim_rig
from rigd.core.devices import PulseBatch
from rigd.core.errors import ConfigError
from rigd.core.host_clock import MONOTONIC
from rigd.core.settings import TriggerSettings
from rigd.take import Take


def test_time_stands_still_until_started() -> None:
    clock = VirtualClock()
    done = threading.Event()

    def sleeper() -> None:
        clock.sleep_until(1000.0)
        done.set()

    th = threading.Thread(target=sleeper)
    th.start()
    assert clock.wait_sleepers(1)
    assert clock.now_us() == 0.0  # nothing moves time before start()
    assert not done.is_set()
    clock.start()
    th.join(10)
    assert done.is_set()
    assert clock.now_us() == 1000.0


def test_a_hold_keeps_time_until_released() -> None:
    clock = VirtualClock()
    clock.start()
    hold = clock.hold()
    woke = threading.Event()

    def sleeper() -> None:
        clock.sleep_until(500.0)
        woke.set()

    th = threading.Thread(target=sleeper)
    th.start()
    assert clock.wait_sleepers(1)
    assert clock.now_us() == 0.0  # the hold keeps it
    assert not woke.is_set()
    hold.release()
    th.join(10)
    assert clock.now_us() == 500.0


def test_sleepers_wake_in_deadline_order_holding_time() -> None:
    """Each holder runs alone at its instant: the order of what they record is the order of
    their deadlines, however the threads are scheduled."""
    clock = VirtualClock()
    seen: list[tuple[str, float]] = []
    lock = threading.Lock()

    def actor(name: str, period: float, n: int) -> None:
        hold = clock.hold()
        t = 0.0
        for _ in range(n):
            t += period
            assert hold.sleep_until(t)
            with lock:
                seen.append((name, clock.now_us()))
        hold.release()

    threads = [threading.Thread(target=actor, args=(n, p, 20)) for n, p in (("a", 3.0), ("b", 5.0))]
    for th in threads:
        th.start()
    clock.start()
    for th in threads:
        th.join(20)
    times = [t for _, t in seen]
    assert times == sorted(times)
    expected = [("a", 3.0 * k) for k in range(1, 21)] + [("b", 5.0 * k) for k in range(1, 21)]
    assert sorted(seen) == sorted(expected)


def test_a_sleeper_leaves_on_its_stop_event_without_moving_time() -> None:
    clock = VirtualClock()
    clock.start()
    hold = clock.hold()
    stop = threading.Event()
    result: list[bool] = []
    th = threading.Thread(target=lambda: result.append(clock.sleep_until(10.0, stop)))
    th.start()
    stop.set()
    th.join(10)
    assert result == [False]
    hold.release()
    assert clock.now_us() == 0.0


def test_a_real_world_stamps_host_time_with_the_monotonic_clock() -> None:
    world = SimWorld("host-real")
    assert world.host_clock is MONOTONIC


def test_a_virtual_world_stamps_host_time_with_epoch_plus_virtual_time() -> None:
    """Host time on the virtual clock moves with virtual time only, from an epoch that is the
    monotonic clock's reading when the world was made (plausible magnitudes)."""
    before = time.monotonic_ns()
    world = SimWorld("host-virtual", clock="virtual")
    after = time.monotonic_ns()
    host = world.host_clock
    assert isinstance(host, VirtualHostClock)
    epoch = host.epoch_ns
    assert before <= epoch <= after
    assert host.now_ns() == epoch  # time has not started: host time stands at the epoch
    assert isinstance(world.clock, VirtualClock)
    world.clock.start()
    world.clock.update(to_us=1234.5678)  # however long the machine took to get here
    assert host.now_ns() == epoch + 1_234_568
    world.clock.update(to_us=2_000_000.0)
    assert host.now_ns() == epoch + 2_000_000_000
    host.adopt_epoch(7)  # a cable follower counts from its lead's epoch
    assert host.now_ns() == 7 + 2_000_000_000


@pytest.mark.parametrize("transport", ["serial", "hid"])
def test_a_virtual_box_holds_each_pulse_until_the_host_has_stamped_its_record(transport: str) -> None:
    """Nothing else holds this world's time: without the box's wait for the host to handle
    each record, time would jump from pulse to pulse while records sat unread and the driver
    would stamp them late. With it, records carry the world's host time of their pulse."""
    name = f"host-read-{transport}"
    reset_world(name)
    trig = open_device("trigger", f"sim://{name}/trigger?clock=virtual&transport={transport}")
    try:
        world = get_world(name)
        host = world.host_clock
        assert isinstance(host, VirtualHostClock)
        assert trig.host_clock is host
        trig.configure(TriggerSettings(rate_hz=1000.0, pulse_width_us=100))
        trig.arm()
        trig.start(40)
        got: list[PulseBatch] = []
        deadline = time.monotonic() + 60.0  # a state to wait for, not a delay
        while sum(len(b) for b in got) < 40:
            assert time.monotonic() < deadline, "the box never sent its 40 records"
            got.append(trig.read_pulses(0.1))
        index = np.concatenate([b.index for b in got])
        host_ns = np.concatenate([b.host_time_ns for b in got]) - host.epoch_ns
        true_ns = {k: round(t * 1000) for k, _, t, _ in world.truth.pulses}
        late_ns = host_ns - np.array([true_ns[int(k)] for k in index])
        assert (late_ns >= 0).all()
        # Stamped before the world moved on (the box waits at most 0.5 s of wall time for the
        # host, so a starved host may stamp a few late, never most of them).
        assert np.median(late_ns) == 0, late_ns.tolist()
    finally:
        trig.close()
        reset_world(name)


def test_a_world_refuses_specs_that_disagree_on_the_clock() -> None:
    reset_world("clock-clash")
    get_world("clock-clash", clock="virtual")
    with pytest.raises(ConfigError, match=r"virtual clock.*clock=real"):
        get_world("clock-clash", clock="real")
    with pytest.raises(ConfigError, match="clock='fast'"):
        get_world("other", clock="fast")
    reset_world("clock-clash")


def _capture(tmp: Path, world: str) -> tuple[Take, int, dict[str, dict[int, float]]]:
    """A virtual take, its world's host epoch and each camera's true exposure starts by counter."""
    reset_world(world)
    config = default_sim_rig(world=world, seed=7, clock="virtual")
    result = run_capture(config, tmp, 0.5)
    assert result.frames == {"cam0": 15, "cam1": 15, "cam2": 15}
    host = get_world(world).host_clock
    assert isinstance(host, VirtualHostClock)
    truth = get_world(world).truth
    exposed = {cam: {c: t for c, t, _ in rows} for cam, rows in truth.frames.items()}
    return Take(result.path), host.epoch_ns, exposed


@pytest.mark.slow
def test_two_virtual_captures_with_the_same_seed_are_identical(tmp_path: Path) -> None:
    """The whole pipeline (pty trigger, EVT decoding, window, sync, finalize) on virtual time:
    frames (pixels and times) and events are the same twice, and so are the frames' host times,
    less their world's epoch: host time is the world's (epoch + virtual time of emission),
    however differently loaded the machine was during the two takes. (An event packet's host
    time is that of the newest device buffer the host read into it, so it depends on when the
    host read: `test_sim_event_sensor` checks the buffers' stamps.)"""
    a, epoch_a, exposed_a = _capture(tmp_path / "a", "det-a")
    b, epoch_b, _ = _capture(tmp_path / "b", "det-b")
    for cam in ("cam0", "cam1", "cam2"):
        fa, fb = a.camera(cam), b.camera(cam)
        assert len(fa) == len(fb) == 15
        assert np.array_equal(fa.timestamps_us, fb.timestamps_us)
        for i in (0, 7, 14):
            assert np.array_equal(fa[i].image, fb[i].image)
        host_a = np.array([f.host_time_ns for f in fa[:]], np.int64) - epoch_a
        host_b = np.array([f.host_time_ns for f in fb[:]], np.int64) - epoch_b
        assert np.array_equal(host_a, host_b)
        # A frame is handed over when its exposure ends, at that virtual instant.
        ends = [exposed_a[cam][f.frame_counter] + f.exposure_us for f in fa[:]]
        assert np.abs(host_a - np.round(np.array(ends) * 1000)).max() <= 1000
    for sensor in ("ev0", "ev1"):
        ea, eb = a.sensor(sensor).events(), b.sensor(sensor).events()
        assert len(ea) > 10_000
        assert np.array_equal(ea.t, eb.t)
        assert np.array_equal(ea.x, eb.x)
        assert np.array_equal(ea.y, eb.y)
        assert np.array_equal(ea.p, eb.p)
    reset_world("det-a")
    reset_world("det-b")


@pytest.mark.slow
def test_a_slow_virtual_world_is_not_cut_by_wall_clock_deadlines(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A virtual rig much slower than real time (here ~40x) still gets all its pulses: no
    wall-clock pulse deadline, no trigger-silence fault while the box answers."""
    import time

    import firmware_sim.event_sensor as es

    real = es.generate_events

    def slow(*args: object, **kw: object) -> object:
        time.sleep(0.15)  # each 5 ms slice of each sensor: far slower than real time
        return real(*args, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(es, "generate_events", slow)
    reset_world("slow-virtual")
    config = default_sim_rig(world="slow-virtual", seed=1, clock="virtual", resolution=(320, 180))
    result = run_capture(config, tmp_path, 0.2)
    reset_world("slow-virtual")
    assert result.frames == {"cam0": 6, "cam1": 6, "cam2": 6}
    assert result.end_reason == "all 6 pulses done", result.end_reason
    with Take(result.path) as take:
        report = take.sync_report
        assert report is not None
        assert not [loss for loss in report.losses if loss.count]
