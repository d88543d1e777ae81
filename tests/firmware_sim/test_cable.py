"""The simulated trigger cable in one process: its spec parameters, its socket's safety, and two
worlds of one name (as two processes would hold them) sharing one wire and one virtual clock."""

from __future__ import annotations

import os
import shutil
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from uuid import uuid4

import pytest

from drivers.registry import DeviceSpec, open_device
from firmware_sim.cable import CableParams, cable_params, parse_cable
from firmware_sim.cable_link import CableFollower, CableLead
from firmware_sim.world import Edge, SimWorld, get_world, reset_world, spec_world
from rigd.core.errors import ConfigError, DeviceError, RigdError
from rigd.core.settings import TriggerSettings


@pytest.fixture
def sock_dir() -> Iterator[Path]:
    """A private directory with a short path (a Unix socket path holds 107 bytes)."""
    d = Path(tempfile.mkdtemp(prefix="cable-", dir="/tmp"))
    yield d
    shutil.rmtree(d, ignore_errors=True)


def spec(query: str, name: str = "w", device: str = "ev0") -> DeviceSpec:
    return DeviceSpec.parse(f"sim://{name}/{device}?{query}")


def wait_for(predicate: object, what: str, timeout_s: float = 10.0) -> None:
    """A state to wait for (bounded), never a fixed delay."""
    deadline = time.monotonic() + timeout_s
    while not predicate():  # type: ignore[operator]
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.005)


def test_cable_params_build_a_query_that_parses_back(sock_dir: Path) -> None:
    path = sock_dir / "c.sock"
    lead = parse_cable(spec(cable_params(path, "lead", 2, wait_s=1.5, stall_s=0)))
    assert lead == CableParams(str(path), "lead", 2, 1.5, 0.0)
    assert lead.wait == 1.5
    assert lead.stall == 0.0
    follow = parse_cable(spec(cable_params(path, "follow")))
    assert follow == CableParams(str(path), "follow", 0, None)
    assert follow.wait == 10.0
    assert parse_cable(spec("seed=3")) is None


@pytest.mark.parametrize(
    ("query", "words"),
    [
        ("cable=/tmp/x.sock", ["cable_role"]),
        ("cable_role=lead&cable_followers=1", ["cable=<socket path>"]),
        ("cable=rel.sock&cable_role=follow", ["cable='rel.sock'", "absolute"]),
        ("cable=/tmp/x.sock&cable_role=boss", ["cable_role='boss'", "lead or follow"]),
        ("cable=/tmp/x.sock&cable_role=lead", ["cable_followers=N"]),
        ("cable=/tmp/x.sock&cable_role=lead&cable_followers=-1", ["cable_followers='-1'", "0..64"]),
        ("cable=/tmp/x.sock&cable_role=follow&cable_followers=1", ["cable_followers", "lead"]),
        ("cable=/tmp/x.sock&cable_role=follow&cable_wait_s=nan", ["cable_wait_s='nan'", "0..600"]),
        ("cable=/tmp/x.sock&cable_role=follow&cable_stall_s=5", ["cable_stall_s", "lead"]),
        (
            "cable=/tmp/x.sock&cable_role=lead&cable_followers=1&cable_stall_s=-1",
            ["cable_stall_s='-1'", "0..3600"],
        ),
        (f"cable=/{'a' * 120}&cable_role=follow", ["longer than a Unix socket path"]),
    ],
)
def test_bad_cable_params_are_refused_naming_the_param(query: str, words: list[str]) -> None:
    with pytest.raises(ConfigError) as err:
        parse_cable(spec(query))
    for word in words:
        assert word in str(err.value)


def test_every_sim_device_kind_takes_the_cable_params(sock_dir: Path) -> None:
    """The spec models accept them, so the check happens in one place (`parse_cable`)."""
    query = cable_params(sock_dir / "c.sock", "follow", wait_s=0.05)
    for kind, device in (("event_sensor", "ev0"), ("rgb_camera", "cam0"), ("trigger", "trigger")):
        with pytest.raises(DeviceError, match=r"no lead world after 0\.05 s"):
            open_device(kind, f"sim://{uuid4().hex}/{device}?{query}")  # type: ignore[call-overload]


def test_the_specs_of_a_world_must_agree_on_the_cable(sock_dir: Path) -> None:
    name = f"agree-{uuid4().hex}"
    path = sock_dir / "c.sock"
    try:
        world = spec_world(spec(cable_params(path, "lead", 1), name))
        assert isinstance(world.cable, CableLead)
        assert spec_world(spec(cable_params(path, "lead", 1), name, "cam0")) is world
        with pytest.raises(ConfigError, match=r"differ in cable_followers"):
            spec_world(spec(cable_params(path, "lead", 2), name))
        with pytest.raises(ConfigError, match=r"differ in cable\b"):
            spec_world(spec(cable_params(sock_dir / "other.sock", "lead", 1), name))
        with pytest.raises(ConfigError, match=r"this spec gives no cable"):
            spec_world(spec("seed=0", name))
    finally:
        reset_world(name)
    assert not path.exists()  # the lead unlinks its socket when its world goes


def test_a_world_without_cable_refuses_a_spec_with_one(sock_dir: Path) -> None:
    name = f"agree-{uuid4().hex}"
    try:
        spec_world(spec("seed=0", name))
        with pytest.raises(ConfigError, match=r"opened with no cable"):
            spec_world(spec(cable_params(sock_dir / "c.sock", "lead", 0), name))
    finally:
        reset_world(name)


def test_the_socket_directory_must_be_private(sock_dir: Path) -> None:
    shared = sock_dir / "shared"
    shared.mkdir()
    os.chmod(shared, 0o777)
    with pytest.raises(ConfigError, match=r"writable by group or others \(mode 777\)"):
        CableLead(SimWorld("w", 0, "virtual"), CableParams(str(shared / "c.sock"), "lead", 0))
    with pytest.raises(ConfigError, match=r"writable by group or others"):
        CableFollower(SimWorld("w", 0, "virtual"), CableParams(str(shared / "c.sock"), "follow", 0, 5.0))
    made = sock_dir / "made" / "deeper"
    lead = CableLead(SimWorld("w", 0, "virtual"), CableParams(str(made / "c.sock"), "lead", 0))
    try:
        assert (made.stat().st_mode & 0o777) == 0o700
        assert ((made / "c.sock").stat().st_mode & 0o777) == 0o600
    finally:
        lead.close()


def test_a_second_lead_is_refused_and_a_stale_socket_replaced(sock_dir: Path) -> None:
    params = CableParams(str(sock_dir / "c.sock"), "lead", 0)
    first = CableLead(SimWorld("w", 0, "virtual"), params)
    try:
        with pytest.raises(DeviceError, match="another lead world already listens"):
            CableLead(SimWorld("w", 0, "virtual"), params)
    finally:
        first.close()
    import socket

    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(params.path)  # a socket file nobody listens on: what a killed lead leaves
    stale.close()
    CableLead(SimWorld("w", 0, "virtual"), params).close()
    (sock_dir / "c.sock").write_text("not a socket")
    with pytest.raises(ConfigError, match="is not a socket"):
        CableLead(SimWorld("w", 0, "virtual"), params)


def test_a_follower_of_another_world_or_seed_is_refused(sock_dir: Path) -> None:
    path = str(sock_dir / "c.sock")
    lead = CableLead(SimWorld("w", 1, "virtual"), CableParams(path, "lead", 0))
    try:
        with pytest.raises(ConfigError, match=r"follower's seed is 2, the lead's 1"):
            CableFollower(SimWorld("w", 2, "virtual"), CableParams(path, "follow"))
        with pytest.raises(ConfigError, match=r"follower's clock is 'real', the lead's 'virtual'"):
            CableFollower(SimWorld("w", 1, "real"), CableParams(path, "follow"))
        with pytest.raises(ConfigError, match=r"follower's world is 'v'"):
            CableFollower(SimWorld("v", 1, "virtual"), CableParams(path, "follow"))
        assert lead.connected == 0
    finally:
        lead.close()


def test_one_virtual_clock_over_the_cable(sock_dir: Path) -> None:
    """Sleepers in both worlds wake in one deadline order; every edge reaches the follower at
    its own instant, before the clock moves past it."""
    path = str(sock_dir / "c.sock")
    a, b = SimWorld("w", 1, "virtual"), SimWorld("w", 1, "virtual")
    lead = CableLead(a, CableParams(path, "lead", 1))
    follower = CableFollower(b, CableParams(path, "follow"))
    seen: list[tuple[Edge, float]] = []
    b.wire.subscribe(lambda e: seen.append((e, b.now_us())))
    order: list[tuple[str, float]] = []
    lock = threading.Lock()

    def actor(world: SimWorld, name: str, period: float, n: int) -> None:
        hold = world.hold()
        for k in range(1, n + 1):
            assert hold.sleep_until(period * k)
            with lock:
                order.append((name, world.now_us()))
        hold.release()

    def box() -> None:
        hold = a.hold()
        for k in range(5):
            assert hold.sleep_until(7.0 * (k + 1))
            a.wire.fire(Edge(True, 7.0 * (k + 1), k))
        hold.release()

    threads = [
        threading.Thread(target=actor, args=(a, "a", 3.0, 20)),
        threading.Thread(target=actor, args=(b, "b", 5.0, 20)),
        threading.Thread(target=box),
    ]
    try:
        for th in threads:
            th.start()
        assert a.clock.wait_sleepers(2)  # type: ignore[union-attr]
        assert b.clock.wait_sleepers(1)  # type: ignore[union-attr]
        assert a.now_us() == b.now_us() == 0.0
        a.clock.start()
        for th in threads:
            th.join(20)
            assert not th.is_alive()
        times = [t for _, t in order]
        assert times == sorted(times)
        assert sorted(order) == sorted(
            [("a", 3.0 * k) for k in range(1, 21)] + [("b", 5.0 * k) for k in range(1, 21)]
        )
        assert [(e.pulse_index, e.true_us, now) for e, now in seen] == [
            (k, 7.0 * (k + 1), 7.0 * (k + 1)) for k in range(5)
        ]
        assert b.now_us() == 100.0
    finally:
        follower.close()
        lead.close()


def test_the_lead_waits_until_a_follower_has_taken_in_an_edge(sock_dir: Path) -> None:
    """A follower's device that is slow to latch an edge (here 20 ms of wall time) still sees
    the lead's clock at the edge's instant: the lead moves on only once the edge is acknowledged."""
    path = str(sock_dir / "c.sock")
    a, b = SimWorld("w", 1, "virtual"), SimWorld("w", 1, "virtual")
    lead = CableLead(a, CableParams(path, "lead", 1))
    follower = CableFollower(b, CableParams(path, "follow"))
    lead_time_at_latch: list[float] = []

    def slow_latch(edge: Edge) -> None:
        time.sleep(0.02)  # widens the window in which a lead that did not wait would move on
        lead_time_at_latch.append(a.now_us())

    b.wire.subscribe(slow_latch)
    later = threading.Thread(
        target=lambda: a.clock.sleep_until(1000.0), daemon=True
    )  # a deadline after the edges
    later.start()

    def box() -> None:
        hold = a.hold()
        for k in range(5):
            assert hold.sleep_until(10.0 * (k + 1))
            a.wire.fire(Edge(True, 10.0 * (k + 1), k))
        hold.release()

    th = threading.Thread(target=box)
    th.start()
    try:
        assert a.clock.wait_sleepers(2)  # type: ignore[union-attr]
        a.clock.start()
        th.join(20)
        later.join(20)
        assert lead_time_at_latch == [10.0, 20.0, 30.0, 40.0, 50.0]
    finally:
        follower.close()
        lead.close()


def test_a_follower_that_hangs_up_is_dropped_and_time_goes_on(sock_dir: Path) -> None:
    path = str(sock_dir / "c.sock")
    a, b = SimWorld("w", 1, "virtual"), SimWorld("w", 1, "virtual")
    lead = CableLead(a, CableParams(path, "lead", 1))
    follower = CableFollower(b, CableParams(path, "follow"))
    stuck = b.hold()  # the follower holds time forever...
    a.clock.start()
    woke = threading.Event()
    threading.Thread(target=lambda: a.clock.sleep_until(50.0) and woke.set(), daemon=True).start()
    assert a.clock.wait_sleepers(1)  # type: ignore[union-attr]
    assert not woke.is_set()  # ...so the lead cannot move
    follower.close()  # ...until it hangs up
    assert woke.wait(10)
    assert lead.connected == 0
    assert b.now_us() == 0.0  # nothing moves a follower without its lead
    stuck.release()
    lead.close()


def test_a_follower_that_stops_answering_is_dropped_after_the_stall_time(sock_dir: Path) -> None:
    """A stopped (not dead) follower owes the lead an acknowledgement: after `cable_stall_s`
    the lead drops it, so the shared time goes on, and the follower finds its lead gone."""
    path = str(sock_dir / "c.sock")
    a, b = SimWorld("w", 1, "virtual"), SimWorld("w", 1, "virtual")
    lead = CableLead(a, CableParams(path, "lead", 1, stall_s=0.2))
    follower = CableFollower(b, CableParams(path, "follow"))
    unblock = threading.Event()
    b.wire.subscribe(lambda e: unblock.wait(30))  # the follower's reader stops at the first edge
    woke = threading.Event()

    def box() -> None:
        hold = a.hold()
        assert hold.sleep_until(10.0)
        a.wire.fire(Edge(True, 10.0, 0))
        assert hold.sleep_until(500.0)  # held up until the follower is dropped
        woke.set()
        hold.release()

    th = threading.Thread(target=box)
    th.start()
    try:
        assert a.clock.wait_sleepers(1)  # type: ignore[union-attr]
        a.clock.start()
        assert woke.wait(20)
        assert lead.connected == 0
        unblock.set()
        wait_for(lambda: follower.dead, "the follower to find its lead gone")
    finally:
        unblock.set()
        th.join(10)
        follower.close()
        lead.close()


def test_a_follower_whose_lead_hangs_up_stops_and_its_world_is_replaced(sock_dir: Path) -> None:
    name = f"spent-{uuid4().hex}"
    path = sock_dir / "c.sock"
    a = SimWorld(name, 0, "virtual")
    lead = CableLead(a, CableParams(str(path), "lead", 1))
    try:
        b = spec_world(spec("clock=virtual&" + cable_params(path, "follow"), name))
        assert isinstance(b.cable, CableFollower)
        lead.close()
        wait_for(lambda: b.cable is not None and b.cable.dead, "the follower to see its lead gone")
        with pytest.raises(DeviceError, match=r"no lead world after 0\.1 s"):
            spec_world(spec("clock=virtual&" + cable_params(path, "follow", wait_s=0.1), name))
    finally:
        reset_world(name)


def test_the_lead_clock_does_not_start_without_its_followers(sock_dir: Path) -> None:
    """The box refuses START (ERR STATE naming the cable) while a follower is missing."""
    name = f"start-{uuid4().hex}"
    query = cable_params(sock_dir / "c.sock", "lead", 1, wait_s=0.1)
    try:
        trig = open_device("trigger", f"sim://{name}/trigger?clock=virtual&{query}")
        with trig:
            trig.configure(TriggerSettings(rate_hz=100.0))
            trig.arm()
            with pytest.raises(
                RigdError, match=r"trigger cable .*c\.sock: 0 of 1 follower\(s\) connected after 0.1 s"
            ):
                trig.start(5)
            world = spec_world(DeviceSpec.parse(f"sim://{name}/trigger?clock=virtual&{query}"))
            assert world.now_us() == 0.0
            assert not world.clock.started  # type: ignore[union-attr]
    finally:
        reset_world(name)


def test_a_follower_world_has_no_trigger_box(sock_dir: Path) -> None:
    path = str(sock_dir / "c.sock")
    name = f"nobox-{uuid4().hex}"
    lead = CableLead(SimWorld(name, 0, "virtual"), CableParams(path, "lead", 1))
    try:
        with pytest.raises(ConfigError, match="its trigger box belongs to the lead world"):
            open_device("trigger", f"sim://{name}/trigger?clock=virtual&{cable_params(path, 'follow')}")
    finally:
        reset_world(name)
        lead.close()


def test_a_real_clock_follower_counts_from_the_leads_epoch(sock_dir: Path) -> None:
    path = str(sock_dir / "c.sock")
    a = SimWorld("w", 0, "real")
    lead = CableLead(a, CableParams(path, "lead", 1))
    b = SimWorld("w", 0, "real")
    follower = CableFollower(b, CableParams(path, "follow"))
    try:
        assert b.clock.epoch_ns == a.clock.epoch_ns  # type: ignore[union-attr]
        got: list[Edge] = []
        b.wire.subscribe(got.append)
        a.await_cable()
        sent = [Edge(k % 2 == 0, a.now_us(), k // 2) for k in range(6)]
        for edge in sent:
            a.wire.fire(edge)
        wait_for(lambda: len(got) == 6, "six edges")
        assert got == sent
    finally:
        follower.close()
        lead.close()


@pytest.mark.slow
def test_the_avr_firmware_box_leads_a_cable_on_the_virtual_clock(sock_dir: Path) -> None:
    """The trigger box as the real firmware under simavr drives the cable like the Python box:
    each of its edges reaches the follower at its own instant of the one clock."""
    from firmware_sim.testing.avr_box import build_firmware, build_harness

    if shutil.which("avr-gcc") is None or not Path("/usr/include/simavr/sim_avr.h").exists():
        pytest.skip("the AVR toolchain or simavr's headers are not installed (gcc-avr, libsimavr-dev)")
    build_firmware()
    build_harness()
    name = f"avr-{uuid4().hex[:8]}"
    path = str(sock_dir / "c.sock")
    trig = open_device(
        "trigger", f"avr://{name}/trigger?mcu=atmega328p&clock=virtual&{cable_params(path, 'lead', 1)}"
    )
    b = SimWorld(name, 0, "virtual")
    follower = CableFollower(b, CableParams(path, "follow"))
    seen: list[tuple[Edge, float]] = []
    b.wire.subscribe(lambda e: seen.append((e, b.now_us())))
    try:
        trig.configure(TriggerSettings(rate_hz=100.0))
        trig.arm()
        trig.start(5)
        wait_for(lambda: len(seen) == 10, "ten edges", timeout_s=60)
        truth = get_world(name)
        rising = [(e.pulse_index, e.true_us) for e, _ in seen if e.rising]
        assert rising == [(k, true_us) for k, _, true_us, _ in truth.truth.pulses]
        assert all(now == e.true_us for e, now in seen)
    finally:
        trig.close()
        follower.close()
        reset_world(name)
