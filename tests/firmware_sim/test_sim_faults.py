"""Fault injection on the sim devices, seen through the host drivers the daemon uses.

Unplug/replug (cameras, event sensors), a camera slower than the trigger (`busy_us`), a hung or
garbled trigger-box link, and the ground-truth journal (`RIGD_SIM_TRUTH_LOG`), which must
hold whole lines even when the process writing it is SIGKILLed.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TypeVar
from uuid import uuid4

import numpy as np
import pytest

from drivers.base import Trigger
from drivers.registry import open_device
from firmware_sim.box_devices import find_trigger_box
from firmware_sim.clock import Hold, VirtualClock
from firmware_sim.testing.wire import fire_pulses
from firmware_sim.world import TRUTH_LOG_ENV, SimWorld, close_truth_journals, get_world, reset_world
from rigd.core.devices import PulseBatch
from rigd.core.errors import ConfigError, DeviceError, DeviceTimeoutError
from rigd.core.events import EventPacket
from rigd.core.frames import Frame
from rigd.core.settings import CameraSettings, EventSensorSettings, TriggerSettings

SMALL = "width=160&height=120"


@pytest.fixture
def world_name() -> Iterator[str]:
    name = f"t-{uuid4().hex}"
    yield name
    reset_world(name)


def fire_for(world: SimWorld, seconds: float, rate_hz: float) -> tuple[threading.Thread, list[float]]:
    """Fire pulses on the wire in a thread for about `seconds`; the list fills with edge times."""
    out: list[float] = []
    n = round(seconds * rate_hz)
    th = threading.Thread(target=lambda: out.extend(fire_pulses(world, n, rate_hz)), daemon=True)
    th.start()
    return th, out


T = TypeVar("T")


def read_until_error(read: Callable[[float], T | None], limit_s: float = 3.0) -> tuple[list[T], DeviceError]:
    """Read frames or event packets until the unplug makes the read raise."""
    items: list[T] = []
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        try:
            item = read(0.05)
        except DeviceError as exc:
            return items, exc
        if item is not None:
            items.append(item)
    raise AssertionError("the device was never unplugged")


def wait_true(world: SimWorld, true_us: float) -> None:
    assert world.sleep_until(true_us + 1000.0)


# --- unplug / replug ----------------------------------------------------------------------


def hold_at(world: SimWorld, true_us: float) -> tuple[Hold, threading.Event]:
    """A hold that lets a virtual world's time run to `true_us` and keeps it there (the event
    is set then), so the test looks at the world at an exact instant."""
    hold = world.hold()
    reached = threading.Event()

    def sleeper() -> None:
        assert hold.sleep_until(true_us)
        reached.set()

    threading.Thread(target=sleeper, name="test-hold-at", daemon=True).start()
    return hold, reached


@pytest.mark.slow
def test_camera_unplug_fails_reads_and_opens_then_replug_continues_on_the_same_clock(
    world_name: str,
) -> None:
    """Real time, with edges fired from a test thread (`fire_for`); the same unplug on
    virtual time is `test_virtual_time_runs_past_an_unplug` and the replay unplug test."""
    spec = f"sim://{world_name}/cam0?{SMALL}&offset_us=1503311&drift_ppm=80&unplug_at_s=0.25&unplug_for_s=0.3"
    world = get_world(world_name)
    cam = open_device("rgb_camera", spec)
    cam.configure(CameraSettings(exposure_us=2000))
    cam.start()
    th, edges = fire_for(world, 0.9, 50.0)
    before, err = read_until_error(cam.read_frame, limit_s=30.0)
    assert "unplugged" in str(err)
    fault = world.unplug_fault("cam0")
    assert fault.end_us - fault.start_us == pytest.approx(0.3e6)
    with pytest.raises(DeviceError, match="no such device"):
        open_device("rgb_camera", spec)  # the host's reconnect attempt, inside the window
    with pytest.raises(DeviceError, match="unplugged"):
        cam.read_frame(0.0)  # the stale handle stays dead
    cam.close()  # closing a dead camera is quiet
    wait_true(world, fault.end_us)

    again = open_device("rgb_camera", spec)  # same spec: replugged, not unplugged again
    again.configure(CameraSettings(exposure_us=2000))
    again.start()
    th.join()
    after = []
    while (f := again.read_frame(0.2)) is not None:
        after.append(f)
    again.close()

    assert before
    assert len(after) >= 5
    # Same device clock: stamps go on, and are exact for the edges that were exposed.
    clock = again.clock  # type: ignore[attr-defined]
    stamps = {clock.stamp(t) for t in edges}
    assert {f.t_exposure_start_us for f in before + after} <= stamps
    assert after[0].t_exposure_start_us > before[-1].t_exposure_start_us
    assert clock.true_at(after[0].t_exposure_start_us) >= fault.end_us
    # The counter goes on from where the unplug left it (counter_reset=1 would restart it).
    counters = [f.frame_counter for f in before + after]
    assert counters == sorted(counters)
    assert len(set(counters)) == len(counters)
    assert after[0].frame_counter > before[-1].frame_counter

    truth = world.truth
    rows = truth.frames["cam0"]
    delivered = {c for c, _, ok in rows if ok}
    assert delivered == set(counters)
    window = [t for t in edges if fault.start_us <= t < fault.end_us]
    assert sorted(t for c, t, ok in rows if c == -1 and not ok) == pytest.approx(window)
    assert len(window) >= 10
    assert truth.unplugged["cam0"] == [(fault.start_us, fault.end_us)]
    assert again.stats().extra["triggers_ignored"] == 0


def test_virtual_time_goes_on_after_a_sleeper_without_a_hold_wakes() -> None:
    clock = VirtualClock()
    clock.start()
    hold = clock.hold()  # keeps time at 0 until the two sleepers are in
    timer = threading.Thread(target=clock.sleep_until, args=(100.0,), daemon=True)  # no hold
    timer.start()
    assert clock.wait_sleepers(1)
    woke = threading.Event()
    threading.Thread(target=lambda: hold.sleep_until(200.0) and woke.set(), daemon=True).start()
    ok = woke.wait(5)
    assert ok, f"virtual time stuck at {clock.now_us()} us with nothing holding it"


def test_virtual_time_runs_past_an_unplug(world_name: str) -> None:
    world = get_world(world_name, clock="virtual")
    cam = open_device("rgb_camera", f"sim://{world_name}/cam0?{SMALL}&unplug_at_s=0.05&clock=virtual")
    cam.start()
    _, reached = hold_at(world, 0.2e6)
    world.clock.start()
    try:
        assert reached.wait(5), f"virtual time stuck at {world.now_us()} us"
    finally:
        cam.close()


@pytest.mark.slow
def test_counter_reset_and_bad_unplug_params(world_name: str) -> None:
    world = get_world(world_name)
    spec = f"sim://{world_name}/cam0?{SMALL}&unplug_at_s=0.05&unplug_for_s=0.1&counter_reset=1"
    cam = open_device("rgb_camera", spec)
    cam.start()
    fire_pulses(world, 3, rate_hz=200)
    wait_true(world, world.unplug_fault("cam0").end_us)
    with pytest.raises(DeviceError, match="unplugged"):
        cam.read_frame(0.0)
    cam.close()
    cam = open_device("rgb_camera", spec)
    cam.start()
    fire_pulses(world, 2, rate_hz=200)
    assert [f.frame_counter for f in (cam.read_frame(1.0), cam.read_frame(1.0)) if f] == [0, 1]
    cam.close()
    for bad, word in (
        ("unplug_at_s=-1", "unplug_at_s"),
        ("unplug_at_s=x", "unplug_at_s"),
        ("unplug_for_s=1", "unplug_for_s needs unplug_at_s"),
        ("unplug_at_s=1&unplug_for_s=0", "unplug_for_s"),
        ("counter_reset=2", "counter_reset"),
        ("busy_us=-5", "busy_us"),
        ("open_delay_s=-1", "open_delay_s"),
        ("open_delay_s=nan", "open_delay_s"),
        ("clock_reset=2", "clock_reset"),
    ):
        with pytest.raises(ConfigError, match=word):
            open_device("rgb_camera", f"sim://{world_name}/cam9?{bad}")
    with pytest.raises(ConfigError, match="unplug_at_s"):
        open_device("event_sensor", f"sim://{world_name}/ev9?unplug_at_s=nan")
    with pytest.raises(ConfigError, match="clock_reset"):
        open_device("event_sensor", f"sim://{world_name}/ev9?clock_reset=x")
    with pytest.raises(ConfigError, match="silent_after"):
        open_device("trigger", f"sim://{world_name}/trigger?silent_after=-1")


def test_event_sensor_unplug_reaches_read_events_and_replug_continues(world_name: str) -> None:
    """On virtual time: unplugged at 0.3 s, looked at 0.4 s, replugged at 0.55 s, read to 0.7 s."""
    spec = (
        f"sim://{world_name}/ev0?{SMALL}&offset_us=412775&drift_ppm=-95&unplug_at_s=0.3&unplug_for_s=0.25"
        "&clock=virtual"
    )
    world = get_world(world_name, clock="virtual")
    sensor = open_device("event_sensor", spec)
    sensor.configure(EventSensorSettings())
    sensor.start()
    hold, reached = hold_at(world, 0.4e6)
    world.clock.start()
    before, err = read_until_error(sensor.read_events, limit_s=60.0)
    assert "unplugged" in str(err)
    assert reached.wait(30)
    fault = world.unplug_fault("ev0")
    assert (fault.start_us, fault.end_us) == (0.3e6, 0.55e6)
    with pytest.raises(DeviceError, match="no such device"):
        open_device("event_sensor", spec)
    sensor.close()
    assert hold.sleep_until(fault.end_us + 1000.0)

    again = open_device("event_sensor", spec)
    again.configure(EventSensorSettings())
    again.start()
    hold.release()
    hold, reached = hold_at(world, 0.7e6)
    after = []
    while not reached.is_set():  # time runs while the host reads (the sensor waits for room)
        if (p := again.read_events(0.05)) is not None:
            after.append(p)
    while (p := again.read_events(0.05)) is not None:
        after.append(p)
    again.stop()  # at 0.7 s exactly: its last slice ends there
    hold.release()
    while (p := again.read_events(0.1)) is not None:
        after.append(p)
    again.close()

    ev_before = np.concatenate([p.events.t for p in before])
    ev_after = np.concatenate([p.events.t for p in after])
    assert len(ev_before) > 0
    assert len(ev_after) > 0
    clock = again.clock  # type: ignore[attr-defined]
    [(lost_from, lost_to)] = world.truth.unplugged["ev0"]
    assert lost_to == fault.end_us
    # Everything the host got lies before the lost span, everything after it on the same clock.
    assert clock.true_at(ev_before.max()) <= lost_from <= fault.start_us
    assert clock.true_at(ev_after.min()) >= fault.end_us
    assert clock.true_at(ev_after.max()) <= 0.7e6
    assert ev_after.min() > ev_before.max()


# --- slow camera --------------------------------------------------------------------------


def test_busy_camera_ignores_every_other_edge_at_30_hz(world_name: str) -> None:
    world = get_world(world_name)
    cam = open_device("rgb_camera", f"sim://{world_name}/cam0?{SMALL}&busy_us=50000")
    cam.configure(CameraSettings(exposure_us=2000))
    cam.start()
    edges = fire_pulses(world, 10, rate_hz=30.0)
    cam.stop()
    frames = []
    while (f := cam.read_frame(0.1)) is not None:
        frames.append(f)
    cam.close()
    assert [f.frame_counter for f in frames] == [0, 1, 2, 3, 4]
    assert [f.t_exposure_start_us for f in frames] == [cam.clock.stamp(t) for t in edges[::2]]  # type: ignore[attr-defined]
    assert cam.stats().extra["triggers_ignored"] == 5
    assert world.truth.ignored_triggers["cam0"] == [(i, edges[i]) for i in range(1, 10, 2)]


# --- trigger-box link faults --------------------------------------------------------------


def pulse_thread_alive(world_name: str) -> bool:
    """Is the pulse scheduler of that world's sim trigger box still running?"""
    return any(th.name == f"trigbox-pulses-{world_name}" and th.is_alive() for th in threading.enumerate())


def run_trigger(trig: Trigger, rate_hz: float, seconds: float) -> PulseBatch:
    """Run the box for `seconds` of wall time, reading pulses. Real time on purpose: the link
    fault tests are about the driver's reply timeouts on a real serial link."""
    trig.configure(TriggerSettings(rate_hz=rate_hz, pulse_width_us=1000))
    trig.arm()
    trig.start()
    parts = []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        parts.append(trig.read_pulses(0.05))
    return PulseBatch(
        np.concatenate([p.index for p in parts]),
        np.concatenate([p.t_us for p in parts]),
        np.concatenate([p.host_time_ns for p in parts]),
    )


@pytest.mark.slow
def test_silent_after_hangs_the_link_but_not_the_trigger(world_name: str) -> None:
    world = get_world(world_name)
    trig = open_device("trigger", f"sim://{world_name}/trigger?silent_after=5&reply_timeout_s=0.3")
    box = find_trigger_box(world)
    assert box is not None
    batch = run_trigger(trig, 100.0, 0.4)
    assert batch.index.tolist() == [0, 1, 2, 3, 4]  # then nothing: no records, no gap to recover
    assert box.silent
    n_fired = len(world.truth.pulses)
    assert n_fired > 20  # the wire keeps firing
    with pytest.raises(DeviceTimeoutError):
        trig.pulse_count()
    t = time.monotonic()
    trig.close()  # STOP goes unanswered: one reply timeout, then the link is released
    assert time.monotonic() - t < 1.0
    assert box.closed
    # Closing powered the box down: close() joined its pulse thread, so no pulse can follow
    # (checked as a state, not by watching the wire for a while).
    assert not pulse_thread_alive(world_name)


@pytest.mark.slow
def test_garbage_after_garbles_every_line_and_close_returns(world_name: str) -> None:
    world = get_world(world_name)
    trig = open_device("trigger", f"sim://{world_name}/trigger?garbage_after=5&reply_timeout_s=0.3")
    batch = run_trigger(trig, 100.0, 0.4)
    assert batch.index.tolist() == [0, 1, 2, 3, 4]
    corrupt = trig.link_stats()["corrupt_lines"]  # type: ignore[attr-defined]
    assert corrupt > 20  # one per pulse record since the fault hit
    with pytest.raises(DeviceTimeoutError, match="corrupt line"):
        trig.pulse_count()
    assert len(world.truth.pulses) > 20
    t = time.monotonic()
    trig.close()  # the box hears STOP; its replies are garbage, so the driver gives up soon
    assert time.monotonic() - t < 1.5
    assert not pulse_thread_alive(world_name)  # close joined it: no pulse can follow


# --- ground-truth journal -----------------------------------------------------------------


@pytest.fixture
def journal(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    path = tmp_path / "truth.jsonl"
    monkeypatch.setenv(TRUTH_LOG_ENV, str(path))
    yield path
    close_truth_journals()


@pytest.mark.slow
def test_journal_lines_match_what_the_host_read(world_name: str, journal: Path) -> None:
    trig = open_device("trigger", f"sim://{world_name}/trigger")
    cam = open_device("rgb_camera", f"sim://{world_name}/cam0?{SMALL}")
    sensor = open_device("event_sensor", f"sim://{world_name}/ev0?{SMALL}")
    frames: list[Frame] = []
    packets: list[EventPacket] = []
    try:
        cam.configure(CameraSettings(exposure_us=2000))
        cam.start()
        sensor.start()
        trig.configure(TriggerSettings(rate_hz=50.0, pulse_width_us=1000))
        trig.arm()
        trig.start(12)
        pulses = []
        deadline = time.monotonic() + 0.5
        while time.monotonic() < deadline:
            pulses.append(trig.read_pulses(0.0))
            if (f := cam.read_frame(0.01)) is not None:
                frames.append(f)
            if (p := sensor.read_events(0.01)) is not None:
                packets.append(p)
        cam.stop()
        sensor.stop()
        while (f := cam.read_frame(0.05)) is not None:
            frames.append(f)
        while (p := sensor.read_events(0.05)) is not None:
            packets.append(p)
        pulses.append(trig.read_pulses(0.05))
    finally:
        for dev in (cam, sensor, trig):
            dev.close()

    lines = [json.loads(line) for line in journal.read_text().splitlines()]
    assert {ln["world"] for ln in lines} == {world_name}
    got_frames = [(ln["counter"], ln["t_device_us"]) for ln in lines if ln["kind"] == "frame"]
    assert got_frames == [(f.frame_counter, f.t_exposure_start_us) for f in frames]
    assert len(frames) == 12
    ev_lines = [ln for ln in lines if ln["kind"] == "events"]
    assert len(ev_lines) == len(packets)  # one line per packet read, never per event
    assert [ln["n"] for ln in ev_lines] == [len(p.events) for p in packets]
    assert sum(ln["n"] for ln in ev_lines) > 0
    assert [ln["n_triggers"] for ln in ev_lines] == [len(p.triggers) for p in packets]
    for ln, p in zip(ev_lines, packets, strict=True):
        if len(p.events):
            span = (int(p.events.t[0]), int(p.events.t[-1]))
            assert (ln["t_first_device_us"], ln["t_last_device_us"]) == span
            assert ln["host_time_ns"] >= p.host_time_ns
    pulse_lines = [ln for ln in lines if ln["kind"] == "pulse"]
    read_idx = np.concatenate([b.index for b in pulses]).tolist()
    read_t = np.concatenate([b.t_us for b in pulses]).tolist()
    assert [(ln["index"], ln["t_us"]) for ln in pulse_lines] == list(zip(read_idx, read_t, strict=True))
    assert read_idx == list(range(12))
    assert not any(ln["garbled"] for ln in pulse_lines)
    for kind in ("frame", "events", "pulse"):
        hosts = [ln["host_time_ns"] for ln in lines if ln["kind"] == kind]
        assert hosts == sorted(hosts)


_KILL_CHILD = """
import sys, threading
from firmware_sim.world import TruthJournal
j = TruthJournal(sys.argv[1])
def spam(dev):
    k = 0
    while True:
        j.write('{"dev":"%s","kind":"frame","counter":%d,"host_time_ns":0}' % (dev, k))
        k += 1
for d in ("cam0", "cam1", "cam2"):
    threading.Thread(target=spam, args=(d,), daemon=True).start()
print("go", flush=True)
threading.Event().wait()
"""


def test_journal_survives_sigkill_with_whole_lines(tmp_path: Path) -> None:
    path = tmp_path / "killed.jsonl"
    child = subprocess.Popen(
        [sys.executable, "-c", _KILL_CHILD, str(path)], stdout=subprocess.PIPE, env=dict(os.environ)
    )
    try:
        assert child.stdout is not None
        assert child.stdout.readline().strip() == b"go"
        # Kill it mid-write once it has written a good many lines (a state, not a fixed delay).
        deadline = time.monotonic() + 30.0
        while not path.exists() or path.stat().st_size < 20_000:
            assert time.monotonic() < deadline, "the child wrote too little"
            time.sleep(0.01)
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait()
    text = path.read_text()
    assert text.endswith("\n")  # no torn last line
    lines = [json.loads(line) for line in text.splitlines()]
    assert len(lines) > 100
    for dev in ("cam0", "cam1", "cam2"):
        counters = [ln["counter"] for ln in lines if ln["dev"] == dev]
        assert counters == list(range(len(counters)))  # nothing lost before the kill, in order
