"""replay://: a recorded take played back through the real drivers, and re-captured."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from drivers.registry import DeviceSpec, open_device
from firmware_sim.replay_recording import Recording, rig_to_device
from firmware_sim.world import reset_world
from rigd.app.capture import run_capture
from rigd.app.config import default_sim_rig
from rigd.app.replay import replay_config
from rigd.core.errors import ConfigError
from rigd.core.timebase import ClockMap
from rigd.take import Take

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    reset_world("replay-src")
    config = default_sim_rig(world="replay-src", seed=3, clock="virtual")
    result = run_capture(config, tmp_path_factory.mktemp("src"), 0.5)
    reset_world("replay-src")
    return result.path


def _recapture(recorded: Path, out: Path, **kw: object) -> Take:
    config, duration = replay_config(recorded, **kw)  # type: ignore[arg-type]
    result = run_capture(config, out, duration)
    reset_world(f"replay:{recorded.resolve()}")
    return Take(result.path)


def _same_take(a: Take, b: Take) -> None:
    for cam in a.cameras:
        fa, fb = a.camera(cam), b.camera(cam)
        assert len(fa) == len(fb) > 0
        assert np.array_equal(fa.timestamps_us, fb.timestamps_us)
        for i in range(len(fa)):
            assert np.array_equal(fa[i].image, fb[i].image)
            assert fa[i].frame_counter == fb[i].frame_counter
    for sensor in a.event_sensors:
        ea, eb = a.sensor(sensor).events(), b.sensor(sensor).events()
        assert len(ea) == len(eb) > 0
        for k in "txyp":
            assert np.array_equal(getattr(ea, k), getattr(eb, k)), (sensor, k)
        assert np.array_equal(a.sensor(sensor).triggers.t, b.sensor(sensor).triggers.t)
    ra, rb = a.sync_report, b.sync_report
    assert ra is not None
    assert rb is not None
    for name, fit in ra.devices.items():
        other = rb.devices[name]
        # The same clock maps: rig times agree within 1 us over the take and beyond.
        ma = ClockMap(fit.device_ref_us, fit.rig_ref_us, fit.rate, fit.frac_us)
        mb = ClockMap(other.device_ref_us, other.rig_ref_us, other.rate, other.frac_us)
        device = fit.device_ref_us + np.arange(-60_000_000, 60_000_001, 1_000_000)
        assert np.abs(ma.to_rig_float(device) - mb.to_rig_float(device)).max() < 1.0, name
    assert np.array_equal(a.pulses().t_us, b.pulses().t_us)


@pytest.mark.parametrize("clock", ["virtual", "real"])
def test_a_replayed_take_recaptures_identically(recorded: Path, tmp_path: Path, clock: str) -> None:
    with Take(recorded) as a, _recapture(recorded, tmp_path, clock=clock) as b:
        _same_take(a, b)


def test_replay_fault_switches_reach_the_take(recorded: Path, tmp_path: Path) -> None:
    """drop_frames on a replayed camera: the frame is missing and the take says so."""
    with _recapture(recorded, tmp_path, clock="virtual", faults={"cam1": {"drop_frames": "4"}}) as b:
        with Take(recorded) as a:
            counters = [f.frame_counter for f in b.camera("cam1")]
            assert 4 not in counters
            assert len(counters) == len(a.camera("cam1")) - 1
        report = b.sync_report
        assert report is not None
        assert 4 in report.devices["cam1"].dropped_frames


def test_rig_to_device_is_exact_where_a_preimage_exists() -> None:
    rng = np.random.default_rng(0)
    for rate in (1.0 - 95e-6, 1.0 + 100e-6, 1.0):
        cmap = ClockMap(412_775, 1_000_000, rate, 0.37)
        d = np.sort(rng.integers(0, 60_000_000, 200_000)).astype(np.int64) + 412_775
        r = cmap.to_rig(d)
        back, inexact = rig_to_device(cmap, r)
        assert inexact == 0
        assert np.array_equal(cmap.to_rig(back), r)


def test_replay_refuses_what_it_cannot_play(recorded: Path, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no camera 'cam9'"):
        open_device("rgb_camera", f"replay://{recorded.resolve()}?device=cam9")
    with pytest.raises(ConfigError, match="absolute"):
        open_device("rgb_camera", "replay://relative/take.h5?device=cam0")
    with pytest.raises(ConfigError, match="no take file"):
        open_device("rgb_camera", f"replay://{tmp_path}/missing.h5?device=cam0")
    with pytest.raises(ConfigError, match=r"\?device=NAME"):
        open_device("event_sensor", f"replay://{recorded.resolve()}")
    with pytest.raises(ConfigError, match="no device"):
        replay_config(recorded, faults={"cam7": {"drop_frames": "1"}})
    bad = tmp_path / "text.h5"
    bad.write_text("not a take")
    with pytest.raises(ConfigError, match=r"text\.h5"):
        Recording(bad)
    reset_world(f"replay:{recorded.resolve()}")
    assert DeviceSpec.parse(f"replay://{recorded.resolve()}?device=ev0").scheme == "replay"


def test_replay_unplug_and_clock_reset(recorded: Path, tmp_path: Path) -> None:
    """A replayed camera unplugged for 0.1 s that comes back counting from 0: the take loses
    the frames of the window, re-ties the restarted clock, and the frames it kept have the
    recorded rig times."""
    faults = {"cam2": {"unplug_at_s": "0.2", "unplug_for_s": "0.1", "clock_reset": "1"}}
    config, duration = replay_config(recorded, clock="virtual", faults=faults)
    result = run_capture(config, tmp_path, duration, reconnect_interval_s=0.02)
    reset_world(f"replay:{recorded.resolve()}")
    with Take(recorded) as a, Take(result.path) as b:
        ta, tb = a.camera("cam2").timestamps_us, b.camera("cam2").timestamps_us
        assert 0 < len(tb) < len(ta)
        # Every kept frame at its recorded rig time, to the microseconds the camera's fit moves
        # by when its restarted clock is re-tied: the drift behind the tie is fitted over the
        # 0.2 s before the gap with 2 us trigger jitter (docs/benchmarks.md, --replug; measured
        # up to 8 us here), so the bound is that of the tie, not of the replay.
        nearest = ta[np.abs(tb[:, None] - ta[None, :]).argmin(axis=1)]
        assert np.abs(tb - nearest).max() <= 20
        report = b.sync_report
        assert report is not None
        assert any(loss.device == "cam2" for loss in report.losses)


def test_preloaded_cameras_cycle_frames_held_in_memory(recorded: Path, tmp_path: Path) -> None:
    """preload=N: the recorded times and counters, the first N images in turn."""
    config, duration = replay_config(recorded, clock="virtual")
    for cam_config in config.cameras:
        cam_config.spec += "&preload=2"
    result = run_capture(config, tmp_path, duration)
    reset_world(f"replay:{recorded.resolve()}")
    with Take(recorded) as a, Take(result.path) as b:
        for cam in a.cameras:
            fa, fb = a.camera(cam), b.camera(cam)
            assert len(fa) == len(fb) > 2
            assert np.array_equal(fa.timestamps_us, fb.timestamps_us)
            assert not np.array_equal(fa[2].image, fa[0].image)  # the scene moves: a replay differs
            for i in range(len(fb)):
                assert np.array_equal(fb[i].image, fa[i % 2].image)
                assert fb[i].frame_counter == fa[i].frame_counter
    with pytest.raises(ConfigError, match="preload"):
        open_device("rgb_camera", f"replay://{recorded}?device=cam0&preload=-1")


def test_a_full_queue_in_real_time_counts_the_events_it_gave_up(recorded: Path) -> None:
    """A reader that falls behind a real-time replay: every buffer the full queue gives up is
    counted with its events (`device_dropped`, the capture's loss ledger reads it), so what was
    read plus what was dropped is what the replay sliced."""
    config, _ = replay_config(recorded, clock="real", faults={"ev0": {"buffer_packets": "1"}})
    [ev_cfg] = [s for s in config.event_sensors if s.name == "ev0"]
    trigger = open_device("trigger", config.trigger.spec)
    sensor = open_device("event_sensor", ev_cfg.spec)
    try:
        trigger.configure(config.trigger.settings)
        sensor.configure(ev_cfg.settings)
        sensor.start()
        trigger.arm()
        trigger.start()
        # Nobody reads: with one slot, every buffer after the first overflows. Waits for the
        # drops themselves (the bound only ends a test that would hang).
        deadline = time.monotonic() + 60
        while sensor.stats().extra["packets_dropped"] < 3:
            assert time.monotonic() < deadline, sensor.stats()
            time.sleep(0.01)
        trigger.stop()
        sensor.stop()
        read = edges = 0
        while (packet := sensor.read_events(0.0)) is not None:
            read += packet.n_events
            edges += len(packet.triggers)
        stats = sensor.stats()
    finally:
        sensor.close()
        trigger.close()
        reset_world(f"replay:{recorded.resolve()}")
    assert stats.device_dropped > 0
    assert read + stats.device_dropped == stats.extra["events"], stats
    assert edges + stats.extra["triggers_dropped"] == stats.extra["triggers"], stats
