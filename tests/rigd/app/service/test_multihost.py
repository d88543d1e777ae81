"""A rig split over daemons: the joined take equals the one-daemon take; hosts that are missing,
killed or clocked differently cost only what they must."""

from __future__ import annotations

import os
import signal
import time
import uuid
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest

from rigd.app.capture.run import run_capture
from rigd.app.commands.service import wait_for_take
from rigd.app.config import RigConfig
from rigd.app.service.client import DaemonRequestError
from rigd.app.service.daemon import Daemon
from rigd.app.testing.daemon import serve_in_thread, small_rig, wait_idle
from rigd.app.testing.multihost import (
    DEFAULT_SPLIT,
    capture_through,
    client_for,
    compare_takes,
    spawn_serve,
    split_rig,
    stop_serve,
)
from rigd.take import Take


@pytest.fixture
def hosts_in_threads(tmp_path: Path) -> Iterator[Any]:
    """Start the daemons of a split rig in threads of this process (one sim world: no cable)."""
    started: list[Daemon] = []

    def start(configs: dict[str, RigConfig], only: tuple[str, ...] | None = None) -> None:
        for h in reversed(list(configs)):
            if only is None or h in only:
                d = Daemon(configs[h], metrics=False)
                serve_in_thread(d, f"daemon-{h}")
                started.append(d)

    yield start
    for d in started:
        d.shutdown()


def _world() -> str:
    return f"mh-{uuid.uuid4().hex[:6]}"


def test_split_take_equals_the_single_daemon_take_on_virtual_time(
    tmp_path: Path, hosts_in_threads: Any
) -> None:
    base = small_rig(_world(), clock="virtual")
    configs, dirs = split_rig(base, tmp_path / "split")
    hosts_in_threads(configs)
    with client_for(configs["A"]) as client:
        last = capture_through(client, 1.0)
    assert last["verdict"] == "complete", last
    joined = Path(last["path"])
    assert joined.parent == dirs["A"].takes
    assert sorted(p.name for p in dirs["A"].takes.glob("*.part.h5")) == [
        f"{joined.stem}.{h}.part.h5" for h in "ABC"
    ]
    single = run_capture(small_rig(_world(), clock="virtual"), tmp_path / "single", 1.0)
    diffs = compare_takes(joined, single.path)
    assert [d.what for d in diffs if not d.equal] == [], diffs
    assert {d.what for d in diffs} >= {"pulses", "events ev0", "events ev1", "frames cam0", "sync ev1"}


def test_a_capture_is_asked_of_the_coordinator(tmp_path: Path, hosts_in_threads: Any) -> None:
    configs, _ = split_rig(small_rig(_world(), clock="virtual"), tmp_path)
    hosts_in_threads(configs, only=("B",))
    with client_for(configs["B"]) as client, pytest.raises(DaemonRequestError) as err:
        client.call("capture", duration_s=1.0)
    assert "this daemon is host B" in str(err.value)
    assert "host A" in str(err.value)


def test_a_host_that_does_not_answer_fails_the_start_before_any_pulse(
    tmp_path: Path, hosts_in_threads: Any
) -> None:
    configs, dirs = split_rig(small_rig(_world(), clock="virtual"), tmp_path)
    hosts_in_threads(configs, only=("A", "B"))  # C never started
    with client_for(configs["A"], timeout_s=60) as client:
        with pytest.raises(DaemonRequestError) as err:
            client.call("capture", timeout_s=120, duration_s=1.0)
        message = str(err.value)
        assert "host C" in message
        assert configs["A"].hosts["C"].control in message
        assert "no pulse was sent" in message
        assert client.call("status")["state"] == "idle"
    # No joined take; the coordinator's part says why it failed, before any pulse.
    parts = list(dirs["A"].takes.glob("*.h5"))
    assert [p.name.endswith(".A.part.h5") for p in parts] == [True]
    with Take(parts[0]) as take:
        assert take.status == "failed"
        assert len(take.pulses()) == 0
    with client_for(configs["B"]) as b:
        t = wait_idle(b)  # B was armed, then disarmed: its part ends with no pulse
    assert t["last_take"]["path"].endswith(".B.part.h5")


def test_a_host_with_another_config_is_refused_naming_the_field(
    tmp_path: Path, hosts_in_threads: Any
) -> None:
    configs, _ = split_rig(small_rig(_world(), clock="virtual"), tmp_path)
    data = configs["C"].model_dump(mode="json")
    data["writer"]["flush_interval_s"] = 2.5
    configs = {**configs, "C": RigConfig.from_data(data)}
    hosts_in_threads(configs)
    with client_for(configs["A"], timeout_s=60) as client, pytest.raises(DaemonRequestError) as err:
        client.call("capture", timeout_s=120, duration_s=1.0)
    assert "host C" in str(err.value)
    assert "differs from this host's in writer" in str(err.value)


# -- processes: loopback TCP with Curve keys ------------------------------------------------------


def _processes(
    tmp_path: Path, clock: str, wall_clock_s: dict[str, float] | None = None
) -> tuple[dict[str, RigConfig], Any, dict[str, Any]]:
    from firmware_sim.cable import cable_params

    cable = tmp_path / "cable" / "wire.sock"
    cable.parent.mkdir(mode=0o700, parents=True)
    tails = {
        "A": cable_params(cable, "lead", 2),
        "B": cable_params(cable, "follow"),
        "C": cable_params(cable, "follow"),
    }
    base = small_rig(_world(), clock=clock)  # type: ignore[arg-type]
    configs, dirs = split_rig(base, tmp_path / "split", tcp=True, spec_tail=tails, split=DEFAULT_SPLIT)
    procs = {}
    for h in ("C", "B", "A"):
        procs[h] = spawn_serve(
            configs[h],
            tmp_path / f"{h}.json",
            tmp_path / f"{h}.log",
            host=h,
            wall_clock_s=(wall_clock_s or {}).get(h, 0.0),
        )
    return configs, dirs, procs


@pytest.mark.slow
def test_sigkill_of_a_host_costs_only_its_devices_and_recover_plus_gather_completes(tmp_path: Path) -> None:
    configs, dirs, procs = _processes(tmp_path, "real")
    try:
        client = client_for(configs["A"], "A", timeout_s=30)
        res = client.call("capture", timeout_s=120, duration_s=6.0)
        joined = Path(res["take"])
        with client_for(configs["C"], "C") as c:  # C records before it dies
            while c.call("status")["pulses"] < 60:
                time.sleep(0.1)
        os.kill(procs["C"].pid, signal.SIGKILL)
        procs["C"].wait()
        last = wait_for_take(client, str(joined))
        client.close()
        assert last["verdict"] == "degraded", last
        assert any("ev1" in r for r in last["verdict_reasons"]), last["verdict_reasons"]
        with Take(joined) as take:  # A's and B's devices complete
            assert len(take.pulses()) == 180
            assert len(take.camera("cam0")) == 180
            assert take.sync_report is not None
            assert take.sync_report.devices["ev0"].n_matched == 180
        part = dirs["C"].takes / f"{joined.stem}.C.part.h5"
        assert part.exists()
        # C's daemon comes back: it seals its part; gathering on A copies it and re-joins.
        procs["C"] = spawn_serve(configs["C"], tmp_path / "C.json", tmp_path / "C2.log", host="C")
        from typer.testing import CliRunner

        from rigd.app.cli import app

        env = {
            "RIGD_SERVER_PUBLIC_KEY": str(configs["A"].hosts["C"].server_public_key),
            "RIGD_CLIENT_SECRET_KEY": str(configs["A"].hosts["C"].client_secret_key),
        }
        cfg_a = tmp_path / "A.json"
        out = CliRunner().invoke(app, ["takes", "gather", str(joined), "--config", str(cfg_a)], env=env)
        assert out.exit_code == 0, out.output
        with Take(joined) as take:
            ev1 = take.sensor("ev1")
            assert len(ev1) > 0  # kept up to the kill
            assert take.sync_report is not None
            assert "ev1" in take.sync_report.devices
    finally:
        for p in procs.values():
            stop_serve(p)


@pytest.mark.slow
def test_a_host_that_stalls_costs_only_its_devices_and_gather_completes_once_it_is_back(
    tmp_path: Path,
) -> None:
    """SIGSTOP of C mid-take (a hung host, a cut network): the coordinator gives it up after
    HOST_LOST_S and joins without it; once C runs again its part ends on the box's count and
    `rigd takes gather` brings it in."""
    configs, _dirs, procs = _processes(tmp_path, "real")
    stopped = False
    try:
        client = client_for(configs["A"], "A", timeout_s=30)
        joined = Path(client.call("capture", timeout_s=120, duration_s=4.0)["take"])
        with client_for(configs["C"], "C") as c:
            while c.call("status")["pulses"] < 30:
                time.sleep(0.1)
        os.kill(procs["C"].pid, signal.SIGSTOP)
        stopped = True
        last = wait_for_take(client, str(joined))
        client.close()
        assert last["verdict"] == "degraded", last
        assert any("ev1" in r for r in last["verdict_reasons"]), last["verdict_reasons"]
        with Take(joined) as take:
            part_c = next(p for p in take.parts if p.host == "C")
            assert part_c.status == "missing"
            assert part_c.reason is not None
            assert "host C" in part_c.reason
            assert "stopped answering" in part_c.reason
            assert take.sync_report is not None
            assert take.sync_report.devices["ev0"].n_matched == 120
            assert "ev1" not in take.event_sensors
        os.kill(procs["C"].pid, signal.SIGCONT)
        stopped = False
        with client_for(configs["A"], "C", timeout_s=30) as c:
            t = wait_idle(c, timeout=120)
        assert t["last_take"]["path"].endswith(f"{joined.stem}.C.part.h5")
        from typer.testing import CliRunner

        from rigd.app.cli import app

        out = CliRunner().invoke(app, ["takes", "gather", str(joined), "--config", str(tmp_path / "A.json")])
        assert out.exit_code == 0, out.output
        with Take(joined) as take:
            assert len(take.sensor("ev1")) > 0
    finally:
        if stopped:
            os.kill(procs["C"].pid, signal.SIGCONT)
        for p in procs.values():
            stop_serve(p)


@pytest.mark.slow
def test_hosts_whose_wall_clocks_are_30_s_apart_give_the_same_rig_times(tmp_path: Path) -> None:
    runs = {}
    for name, skew in (("same", 0.0), ("skewed", 30.0)):
        configs, _dirs, procs = _processes(tmp_path / name, "virtual", wall_clock_s={"C": skew})
        try:
            with client_for(configs["A"], "A", timeout_s=30) as client:
                last = capture_through(client, 1.0)
            assert last["verdict"] == "complete", last
            runs[name] = Path(last["path"])
            with client_for(configs["A"], "C") as c:
                c_utc = datetime.fromisoformat(c.call("status")["time_utc"])
            assert abs((c_utc - datetime.now(UTC)).total_seconds() - skew) < 5  # C's own wall clock
        finally:
            for p in procs.values():
                stop_serve(p)
    diffs = compare_takes(runs["same"], runs["skewed"])
    assert [d.what for d in diffs if not d.equal] == [], diffs
