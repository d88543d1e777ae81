"""The simulated trigger cable between processes (multiprocessing spawn, as separate daemons):
a follower's event sensor makes exactly what it makes in a one-process world, and a process
that dies costs only itself."""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import shutil
import signal
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any
from uuid import uuid4

import numpy as np
import pytest

from drivers.base import EventSensor
from drivers.registry import open_device
from firmware_sim.cable import CableParams, cable_params
from firmware_sim.cable_link import CableFollower, CableLead
from firmware_sim.world import DeviceClock, Edge, get_world, reset_world
from rigd.core.events import EventArray, TriggerEvents
from rigd.core.settings import TriggerSettings

SEED = 7
SENSOR = f"clock=virtual&seed={SEED}&width=96&height=64&offset_us=1234&drift_ppm=30"
BOX = f"clock=virtual&seed={SEED}&jitter_us=3"
CAMERA = f"clock=virtual&seed={SEED}&width=64&height=48&offset_us=-5000&drift_ppm=-20"
REAL_SENSOR = f"seed={SEED}&width=32&height=24&offset_us=1234&drift_ppm=30"
#: Virtual seconds each run lasts; pulses the box fires in them.
RUN_S = 0.4
PULSES = 9
RATE_HZ = 25.0
_CTX = mp.get_context("spawn")


@pytest.fixture
def sock_dir() -> Iterator[Path]:
    d = Path(tempfile.mkdtemp(prefix="cable-", dir="/tmp"))
    yield d
    shutil.rmtree(d, ignore_errors=True)


def _run_sensor(
    sensor: EventSensor, world_name: str, ready: Callable[[], None], camera: Any
) -> dict[str, Any]:
    """Run a started sensor and camera RUN_S of virtual time from 0 (holding time at the end
    while they stop, so the sensor's last slice ends there) and return what they sent."""
    world = get_world(world_name)
    hold = world.hold()
    reached = threading.Event()

    def sleeper() -> None:
        assert hold.sleep_until(RUN_S * 1e6)
        reached.set()

    threading.Thread(target=sleeper, daemon=True).start()
    assert world.clock.wait_sleepers(2)  # type: ignore[union-attr]  # the sensor's and ours
    ready()
    packets, frames = [], []

    def read(timeout_s: float) -> bool:
        got = False
        if (p := sensor.read_events(timeout_s)) is not None:
            packets.append(p)
            got = True
        if (f := camera.read_frame(timeout_s)) is not None:
            frames.append(f)
            got = True
        return got

    while not reached.is_set():
        read(0.02)
    assert world.now_us() == RUN_S * 1e6
    while read(0.05):
        pass
    sensor.stop()
    camera.stop()
    hold.release()
    while read(0.05):
        pass
    ev = EventArray.concatenate([p.events for p in packets])
    trig = TriggerEvents.concatenate([p.triggers for p in packets])
    extra = sensor.stats().extra
    return {
        "t": ev.t,
        "x": ev.x,
        "y": ev.y,
        "p": ev.p,
        "tt": trig.t,
        "tp": trig.p,
        "tc": trig.channel,
        "frames": [(f.frame_counter, f.t_exposure_start_us, f.image.tobytes()) for f in frames],
        **{k: extra[k] for k in ("triggers_late", "triggers_dropped", "events_generated")},
    }


def _start_box(trig: Any) -> None:
    trig.configure(TriggerSettings(rate_hz=RATE_HZ))
    trig.arm()
    trig.start(PULSES)


def one_process_world(world: str, out: Any) -> None:
    """The reference: the box and the sensor in one world, one process."""
    trig = open_device("trigger", f"sim://{world}/trigger?{BOX}")
    sensor = open_device("event_sensor", f"sim://{world}/ev0?{SENSOR}")
    camera = open_device("rgb_camera", f"sim://{world}/cam0?{CAMERA}")
    sensor.start()
    camera.start()
    out.put(_run_sensor(sensor, world, lambda: _start_box(trig), camera))
    sensor.close()
    camera.close()
    trig.close()


def follower_process(world: str, path: str, out: Any) -> None:
    """The sensor in a follower world; the lead (another process) starts the box once ready."""
    cable = cable_params(path, "follow")
    sensor = open_device("event_sensor", f"sim://{world}/ev0?{SENSOR}&{cable}")
    camera = open_device("rgb_camera", f"sim://{world}/cam0?{CAMERA}&{cable}")
    sensor.start()
    camera.start()

    def ready() -> None:
        out.put("ready")

    out.put(_run_sensor(sensor, world, ready, camera))
    sensor.close()
    camera.close()
    reset_world(world)


def real_follower_process(world: str, path: str, out: Any) -> None:
    """Real time: a sensor in a follower world reads until it has `2 * PULSES` trigger words
    or counted the rest late (bounded in wall time)."""
    spec = f"sim://{world}/ev0?{REAL_SENSOR}&{cable_params(path, 'follow')}"
    sensor = open_device("event_sensor", spec)
    sensor.start()
    out.put("ready")
    words = []
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if (p := sensor.read_events(0.05)) is not None:
            words.append(p.triggers)
        if sum(len(w) for w in words) + sensor.stats().extra["triggers_late"] >= 2 * PULSES:
            break
    sensor.stop()
    while (p := sensor.read_events(0.05)) is not None:
        words.append(p.triggers)
    trig = TriggerEvents.concatenate(words)
    out.put({"tt": trig.t, "tp": trig.p, "late": sensor.stats().extra["triggers_late"]})
    sensor.close()
    reset_world(world)


def lead_process(world: str, path: str, out: Any) -> None:
    """A lead world that fires an edge every ms of virtual time until it is killed."""
    lead_world = get_world(world, SEED, "virtual", CableParams(path, "lead", 1, 30.0))
    lead = lead_world.cable
    assert isinstance(lead, CableLead)
    hold = lead_world.hold()
    lead_world.clock.start()  # waits for the follower
    out.put(lead.connected)
    k = 0
    while True:
        k += 1
        hold.sleep_until(k * 1000.0)
        lead_world.wire.fire(Edge(True, k * 1000.0, k))


def _get(q: Any, proc: Any, timeout_s: float = 120.0) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return q.get(timeout=0.5)
        except queue.Empty:
            assert proc.is_alive() or not q.empty(), f"{proc.name} died (exit code {proc.exitcode})"
            assert time.monotonic() < deadline, f"no answer from {proc.name}"


@pytest.mark.slow
def test_a_follower_makes_what_it_makes_in_one_process(sock_dir: Path) -> None:
    """On the virtual clock, across processes: a follower's event sensor makes the same events
    and trigger words, its camera the same frames, bit for bit."""
    world = f"cable-{uuid4().hex[:8]}"
    q_ref = _CTX.Queue()
    ref_proc = _CTX.Process(target=one_process_world, args=(world, q_ref), name="one-process")
    ref_proc.start()
    path = str(sock_dir / "c.sock")
    trig = open_device("trigger", f"sim://{world}/trigger?{BOX}&{cable_params(path, 'lead', 1, wait_s=30)}")
    q = _CTX.Queue()
    proc = _CTX.Process(target=follower_process, args=(world, path, q), name="follower")
    proc.start()
    try:
        assert _get(q, proc) == "ready"
        _start_box(trig)
        got = _get(q, proc)
        ref = _get(q_ref, ref_proc)
        proc.join(30)
        ref_proc.join(30)
        assert proc.exitcode == 0
        assert ref_proc.exitcode == 0
    finally:
        trig.close()
        reset_world(world)
        for p in (proc, ref_proc):
            if p.is_alive():
                p.kill()
    assert len(ref["t"]) > 1000
    assert len(ref["tt"]) == 2 * PULSES
    for key in ("t", "x", "y", "p", "tt", "tp", "tc"):
        assert np.array_equal(got[key], ref[key]), key
    assert len(ref["frames"]) == PULSES
    assert got["frames"] == ref["frames"]  # counters, exposure times and pixels
    assert got["triggers_late"] == ref["triggers_late"] == 0
    assert got["events_generated"] == ref["events_generated"]


@pytest.mark.slow
def test_a_follower_process_killed_mid_run_costs_only_itself(sock_dir: Path) -> None:
    """SIGKILL of the follower: the lead drops it (a warning) and its virtual time goes on."""
    world = f"cable-{uuid4().hex[:8]}"
    path = str(sock_dir / "c.sock")
    lead_world = get_world(world, SEED, "virtual", CableParams(path, "lead", 1, 30.0))
    lead = lead_world.cable
    assert isinstance(lead, CableLead)
    q = _CTX.Queue()
    proc = _CTX.Process(target=follower_process, args=(world, path, q), name="follower")
    proc.start()
    try:
        assert _get(q, proc) == "ready"
        hold = lead_world.hold()
        lead_world.clock.start()
        assert hold.sleep_until(100_000.0)  # 100 ms of shared time: the follower took part
        assert lead.connected == 1
        os.kill(proc.pid, signal.SIGKILL)  # type: ignore[arg-type]
        proc.join(30)
        assert hold.sleep_until(2_000_000.0)  # far past the follower's run: time went on
        assert lead.connected == 0
        hold.release()
    finally:
        reset_world(world)
        if proc.is_alive():
            proc.kill()


@pytest.mark.slow
def test_a_follower_whose_lead_process_dies_stops_and_closes(sock_dir: Path) -> None:
    world = f"cable-{uuid4().hex[:8]}"
    path = str(sock_dir / "c.sock")
    q = _CTX.Queue()
    proc = _CTX.Process(target=lead_process, args=(world, path, q), name="lead")
    proc.start()
    try:
        spec = f"sim://{world}/ev0?{SENSOR}&{cable_params(path, 'follow', wait_s=60)}"
        sensor = open_device("event_sensor", spec)
        sensor.start()
        assert _get(q, proc) == 1
        follower_world = get_world(world)
        cable = follower_world.cable
        assert isinstance(cable, CableFollower)
        while cable.edges < 20:  # edges arrive, the sensor reads them
            sensor.read_events(0.05)
        os.kill(proc.pid, signal.SIGKILL)  # type: ignore[arg-type]
        proc.join(30)
        deadline = time.monotonic() + 30
        while not cable.dead:
            sensor.read_events(0.05)
            assert time.monotonic() < deadline
        stopped_at = follower_world.now_us()
        sensor.stop()
        while sensor.read_events(0.05) is not None:
            pass
        sensor.close()
        assert follower_world.now_us() == stopped_at  # nothing moves it any more
        assert stopped_at > 0
    finally:
        reset_world(world)
        if proc.is_alive():
            proc.kill()


@pytest.mark.slow
def test_a_real_clock_follower_stamps_the_leads_edges_at_their_true_times(sock_dir: Path) -> None:
    """Real time: the follower counts from the lead's epoch, so its sensor stamps each edge at
    the true time the lead's box fired it (or counts it late, never silently)."""
    world = f"cable-{uuid4().hex[:8]}"
    path = str(sock_dir / "c.sock")
    trig = open_device(
        "trigger", f"sim://{world}/trigger?seed={SEED}&{cable_params(path, 'lead', 1, wait_s=30)}"
    )
    q = _CTX.Queue()
    proc = _CTX.Process(target=real_follower_process, args=(world, path, q), name="follower")
    proc.start()
    try:
        assert _get(q, proc) == "ready"
        _start_box(trig)
        got = _get(q, proc)
        proc.join(30)
        assert proc.exitcode == 0
        truth = get_world(world).truth.pulses
    finally:
        trig.close()
        reset_world(world)
        if proc.is_alive():
            proc.kill()
    assert len(truth) == PULSES
    sensor_clock = DeviceClock(1234.0, 30.0)
    expected = sorted(
        [(sensor_clock.stamp(true_us), 1) for _, _, true_us, _ in truth]
        + [(sensor_clock.stamp(true_us + 1000.0), 0) for _, _, true_us, _ in truth]
    )
    stamped = list(zip(got["tt"].tolist(), got["tp"].tolist(), strict=True))
    assert len(stamped) + got["late"] == 2 * PULSES
    assert set(stamped) <= set(expected)  # each edge it got, at the lead's true time
