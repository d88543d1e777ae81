"""End to end: `run_capture` on the simulated rig, scored against the simulator's truth."""

from __future__ import annotations

import json
import uuid
from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from firmware_sim.world import GroundTruth, get_world
from rigd.app.capture import CaptureResult, run_capture
from rigd.app.cli import app
from rigd.app.config import RigConfig, default_sim_rig
from rigd.core.errors import ConfigError
from rigd.core.timebase import ClockMap
from rigd.take.reader import Take

RES = (320, 180)


def _rig(world: str, **faults: str) -> RigConfig:
    cfg = default_sim_rig(world=world, resolution=RES, pixel_format="mono8")
    if "trigger" in faults:
        cfg.trigger.spec += "&" + faults["trigger"]
    for cam in cfg.cameras:
        if cam.name in faults:
            cam.spec += "&" + faults[cam.name]
    return cfg


@pytest.fixture(scope="module")
def faulty_capture(tmp_path_factory: pytest.TempPathFactory) -> tuple[CaptureResult, GroundTruth]:
    world = f"e2e-{uuid.uuid4().hex[:8]}"
    cfg = _rig(world, trigger="drop_pulses=7,31&garbage_every=15", cam1="drop_frames=4,20")
    res = run_capture(cfg, tmp_path_factory.mktemp("takes"), 2.0)
    return res, get_world(world).truth


def _truth_rig(truth: GroundTruth, device: str, t_device: np.ndarray) -> np.ndarray:
    dev, box = truth.clocks[device], truth.clocks["trigger"]
    true_us = (t_device.astype(np.float64) - dev.offset_us) / dev.rate
    return box.offset_us + true_us * box.rate


@pytest.mark.slow
def test_take_has_every_frame_and_events(faulty_capture: tuple[CaptureResult, GroundTruth]) -> None:
    res, _ = faulty_capture
    with Take(res.path) as take:
        assert take.status == "complete"
        for cam in ("cam0", "cam2"):
            assert abs(len(take.camera(cam)) - 58) <= 1  # 60 pulses, 2 dropped by the box
        assert len(take.camera("cam1")) == 56  # and 2 frames lost in transport
        for sensor in ("ev0", "ev1"):
            ev = take.sensor(sensor).events()
            assert len(ev) > 1000
            assert ev.t.dtype == np.int64
            assert (np.diff(ev.t) >= 0).all()
        for cam in take.cameras:
            assert (np.diff(take.camera(cam).timestamps_us) > 0).all()


def test_injected_faults_are_reported(faulty_capture: tuple[CaptureResult, GroundTruth]) -> None:
    res, _ = faulty_capture
    rep = res.report
    assert rep.n_pulses == 60
    assert rep.device_counters["cam1"]["transport_dropped"] == 2
    assert rep.device_counters["ev0"]["bytes_decoded"] > 0
    # Garbage on the serial line was seen, and every pulse record it hit was read back.
    assert rep.trigger_link["corrupt_lines"] > 0
    assert rep.trigger_link["unrecovered_pulses"] == 0
    assert rep.pulses_missing_from_box_log == []
    assert rep.pulses_seen_by_no_device == [7, 31]
    cam1 = rep.devices["cam1"]
    assert cam1.dropped_frames == [4, 20]
    for name in ("cam0", "cam2", "ev0", "ev1"):
        assert rep.devices[name].missing_pulses == [7, 31]
        assert rep.devices[name].dropped_frames == []


def test_sync_accuracy_against_ground_truth(faulty_capture: tuple[CaptureResult, GroundTruth]) -> None:
    res, truth = faulty_capture
    with Take(res.path) as take:
        for cam in take.cameras:
            fr = take.camera(cam)
            with h5py.File(res.path, "r") as f:
                counters = f[f"frames/{cam}/frame_counter"][:]
            true_by_counter = {c: t for c, t, _ in truth.frames[cam]}
            box = truth.clocks["trigger"]
            expected = np.array([box.at(true_by_counter[int(c)]) for c in counters])
            err = fr.timestamps_us - expected
            assert np.sqrt(np.mean(err**2)) <= 1.0, cam
        for sensor in take.event_sensors:
            d = res.report.devices[sensor]
            cmap = ClockMap(d.device_ref_us, d.rig_ref_us, d.rate, d.frac_us)
            t_rig = take.sensor(sensor).events().t
            t_dev = cmap.to_device(t_rig)
            err = t_rig - _truth_rig(truth, sensor, t_dev)
            assert np.sqrt(np.mean(err**2)) <= 1.0, sensor
            assert abs(d.drift_ppm - truth.clocks[sensor].drift_ppm + truth.clocks["trigger"].drift_ppm) < 5


@pytest.mark.slow
def test_cli_capture_and_inspect_json(tmp_path: Path) -> None:
    cfg = _rig(f"cli-{uuid.uuid4().hex[:8]}")
    cfg_path = tmp_path / "rig.json"
    cfg_path.write_text(cfg.model_dump_json())
    runner = CliRunner()
    r = runner.invoke(app, ["capture", "--config", str(cfg_path), "--duration", "1", "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    take_path = next(tmp_path.glob("*.h5"))
    assert str(take_path) in r.output
    r = runner.invoke(app, ["inspect", str(take_path), "--json"])
    assert r.exit_code == 0, r.output
    summary = json.loads(r.output)
    assert summary["status"] == "complete"
    thumbs = tmp_path / "sheet.png"
    r = runner.invoke(app, ["inspect", str(take_path), "--thumbnails", str(thumbs)])
    assert r.exit_code == 0, r.output
    assert thumbs.stat().st_size > 1000


def test_bad_config_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "rig.toml"
    bad.write_text('name = "x"\n[trigger]\nspec = "sim://w/trigger"\nsettings = { rate_hz = -3 }\n')
    r = CliRunner().invoke(app, ["capture", "--config", str(bad), "--out", str(tmp_path)])
    assert r.exit_code == 2
    assert "trigger.settings.rate_hz" in r.output


@pytest.mark.slow
def test_master_slave_event_sensors_share_a_clock(tmp_path: Path) -> None:
    world = f"ms-{uuid.uuid4().hex[:8]}"
    cfg = _rig(world)
    cfg.cameras = cfg.cameras[:1]
    ev0, ev1 = cfg.event_sensors
    ev0.settings.sync_mode = "master"
    ev1.settings.sync_mode = "slave"
    ev1.settings.sync_master = "ev0"
    ev1.settings.enable_trigger_in = False  # the slave has no trigger cable, only the sync cable
    res = run_capture(RigConfig.model_validate(cfg.model_dump()), tmp_path, 1.0)
    rep = res.report
    assert rep.devices["ev1"].shares_clock_with == "ev0"
    assert rep.devices["ev1"].clock_from == "master"
    assert rep.devices["ev1"].missing_pulses == []
    assert rep.devices["ev0"].clock_from == "own_pulses"
    truth = get_world(world).truth
    with Take(res.path) as take:
        assert len(take.sensor("ev1").triggers) == 0
        t_rig = take.sensor("ev1").events().t
        assert len(t_rig) > 1000
        d = rep.devices["ev1"]
        t_dev = ClockMap(d.device_ref_us, d.rig_ref_us, d.rate, d.frac_us).to_device(t_rig)
        err = t_rig - _truth_rig(truth, "ev1", t_dev)
        assert np.sqrt(np.mean(err**2)) <= 1.0
        cfg_back = RigConfig.model_validate(take.config)
        assert cfg_back.event_sensors[1].settings.sync_mode == "slave"


def test_slave_without_master_is_rejected() -> None:
    cfg = _rig("unused").model_dump()
    cfg["event_sensors"][1]["settings"]["sync_mode"] = "slave"
    cfg["event_sensors"][1]["settings"]["sync_master"] = "ev0"
    with pytest.raises(ConfigError, match="not an event sensor of this rig in sync_mode master"):
        RigConfig.from_data(cfg)


@pytest.mark.slow
def test_capture_with_the_full_pixel_model(tmp_path: Path) -> None:
    """The rig's sim event sensors running the seeded pixel model (mismatch + shot noise)."""
    cfg = default_sim_rig(world=f"pm-{uuid.uuid4().hex[:8]}", resolution=(160, 90), pixel_format="mono8")
    cfg.cameras = cfg.cameras[:1]
    for sen in cfg.event_sensors:
        sen.spec += "&pixel_model=full&sigma=0.03&shot_hz=1"
    res = run_capture(cfg, tmp_path, 1.0)
    for name in ("ev0", "ev1"):
        assert res.events[name] > 0
        dev = res.report.devices[name]
        assert dev.missing_pulses == []
        assert dev.residual_rms_us < 5.0
    with Take(res.path) as take:
        assert "pixel_model=full" in take.config["event_sensors"][0]["spec"]


@pytest.mark.slow
def test_a_sensor_that_sees_nothing_does_not_cost_the_take(tmp_path: Path) -> None:
    """ev1 sees no contrast (its threshold is far above any change in the scene): the take
    completes with everything the others recorded, and says ev1 recorded no events."""
    cfg = default_sim_rig(world=f"dark-{uuid.uuid4().hex[:8]}", resolution=(160, 90), pixel_format="mono8")
    cfg.event_sensors[1].spec += "&threshold=1000"
    res = run_capture(cfg, tmp_path, 1.0)
    assert res.events["ev1"] == 0
    assert res.events["ev0"] > 0
    assert all(n == 30 for n in res.frames.values())
    assert any(w.startswith("ev1: recorded no events") for w in res.report.warnings), res.report.warnings
    with Take(res.path) as take:
        assert take.status == "complete"
        assert len(take.sensor("ev1").events().t) == 0
        assert len(take.sensor("ev0").events().t) == res.events["ev0"]
