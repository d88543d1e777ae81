"""Crash safety: SIGKILLed writers leave takes that open, keep every flushed item, and seal.

The synthetic rig has an exactly known clock relation (device time = rig time + a constant
per device; pulses every PERIOD us; the event sensor's trigger-in edges at the pulses), so
the rig times of a recovered take can be asserted exactly.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import pytest
import typer
from typer.testing import CliRunner

import rigd.take.finalize as finalize_mod
from rigd.app.commands.recover import recover_command
from rigd.app.config import CameraConfig, EventSensorConfig, RigConfig, TriggerConfig
from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.errors import TakeError, TakeFormatError
from rigd.core.events import EventArray, TriggerEvents
from rigd.core.frames import Frame
from rigd.core.layout import Root
from rigd.core.schema import LossRecord, SyncReport
from rigd.core.settings import TriggerSettings, WriterConfig
from rigd.core.timebase import ClockMap
from rigd.take import Take, TakeWriter, find_unfinished, open_take, recover_take, validate_take

ROOT = Path(__file__).parents[2]
W, H = 64, 48
CAM_SHAPE = (6, 8)
PERIOD = 33_333
RIG0 = 5_000_000  # rig time of pulse 0
OFF_EV = 1_234_567  # ev0 device time = rig time + OFF_EV
OFF_CAM = 777_001  # cam0 device time = rig time + OFF_CAM
HOST0 = 10**12  # host monotonic ns at rig time 0
EV_PER_STEP = 300
CHUNK = 1024
WRITER_CFG = WriterConfig(event_chunk=CHUNK, event_compression="lz4")


def rig_config_json() -> str:
    return RigConfig(
        name="crash-rig",
        trigger=TriggerConfig(spec="sim://t/trigger", settings=TriggerSettings(rate_hz=1e6 / PERIOD)),
        cameras=[CameraConfig(name="cam0", spec="sim://t/cam0")],
        event_sensors=[EventSensorConfig(name="ev0", spec="sim://t/ev0")],
        writer=WRITER_CFG,
    ).model_dump_json()


def open_writer(
    path: Path,
    flush_interval_s: float | None = 0.2,
    *,
    config: WriterConfig = WRITER_CFG,
    evt_format: str | None = None,
) -> TakeWriter:
    """The test rig's writer; `evt_format`: its event sensor's packets carry EVT words."""
    w = TakeWriter(
        path,
        rig_config_json=rig_config_json(),
        take_id=path.stem,
        config=config,
        rigd_version="test",
        flush_interval_s=flush_interval_s,
    )
    w.add_trigger(DeviceInfo(kind="trigger", spec="sim://t/trigger"))
    w.add_camera("cam0", DeviceInfo(kind="rgb_camera", spec="sim://t/cam0"), CAM_SHAPE, np.uint8, "{}")
    w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="sim://t/ev0"), W, H, "{}", evt_format)
    return w


@dataclass(frozen=True)
class Step:
    """Everything the rig delivers for pulse k."""

    pulse: PulseBatch
    frame: Frame
    events: EventArray
    triggers: TriggerEvents
    packet_host_ns: int


def step(k: int) -> Step:
    rig = RIG0 + k * PERIOD
    host = HOST0 + rig * 1000 + 300_000  # 0.3 ms after the pulse
    img = np.full(CAM_SHAPE, k % 251, np.uint8)
    img[0, 0] = k // 251 % 256
    rng = np.random.default_rng(k)
    t = rig + OFF_EV + np.sort(rng.integers(0, PERIOD, EV_PER_STEP))
    ev = EventArray.from_arrays(
        rng.integers(0, W, EV_PER_STEP), rng.integers(0, H, EV_PER_STEP), rng.integers(0, 2, EV_PER_STEP), t
    )
    trig_t = np.array([rig + OFF_EV, rig + OFF_EV + 1000], np.int64)
    return Step(
        PulseBatch(np.array([k], np.int64), np.array([rig], np.int64), np.array([host], np.int64)),
        Frame(img, rig + OFF_CAM, 5000, k, host + 2_000_000),
        ev,
        TriggerEvents(trig_t, np.array([1, 0], np.uint8), np.zeros(2, np.uint8)),
        host + 1_000_000,
    )


def append_step(w: TakeWriter, k: int) -> None:
    s = step(k)
    w.append_pulses(s.pulse)
    w.append_frame("cam0", s.frame)
    w.append_events("ev0", s.events)
    w.append_triggers("ev0", s.triggers, s.packet_host_ns)


def journal(k: int) -> dict[str, object]:
    return {
        "losses": [LossRecord(device="ev0", what="events", count=k, reason="test: queue full").model_dump()],
        "device_counters": {"ev0": {"delivered": k * EV_PER_STEP}},
        "failed_devices": {},
        "trigger_link": {"corrupt_lines": 1},
        "warnings": [f"flushed after step {k}"],
    }


@dataclass
class Expected:
    """The first n steps, concatenated, in device time."""

    pulse_t: np.ndarray
    frame_t: np.ndarray
    images: np.ndarray
    ev: EventArray
    trig_t: np.ndarray
    trig_host: np.ndarray


def expected(n: int) -> Expected:
    steps = [step(k) for k in range(n)]
    return Expected(
        np.array([s.pulse.t_us[0] for s in steps], np.int64),
        np.array([s.frame.t_exposure_start_us for s in steps], np.int64),
        np.stack([s.frame.image for s in steps]) if steps else np.empty((0, *CAM_SHAPE), np.uint8),
        EventArray.concatenate([s.events for s in steps]),
        np.concatenate([s.triggers.t for s in steps]) if steps else np.empty(0, np.int64),
        np.repeat([s.packet_host_ns for s in steps], 2).astype(np.int64),
    )


def _kill_script(path: Path, kill_at_append: int | None = None) -> str:
    """The writer loop; with kill_at_append it SIGKILLs itself at that column write (between
    the column appends of one flush, the moment a timed kill rarely hits)."""
    return textwrap.dedent(
        f"""
        import os, signal, sys, time
        from pathlib import Path
        import rigd.take.sinks as sinks
        from tests.rigd.test_take_recover import append_step, journal, open_writer
        KILL_AT = {kill_at_append!r}
        if KILL_AT is not None:
            calls = [0]
            def killing(real):
                def write(*args):
                    calls[0] += 1
                    if calls[0] == KILL_AT:
                        os.kill(os.getpid(), signal.SIGKILL)
                    real(*args)
                return write
            sinks.append_rows = killing(sinks.append_rows)
            sinks._write_slot = killing(sinks._write_slot)
        w = open_writer(Path({str(path)!r}), flush_interval_s=0.2)
        print("START", flush=True)
        k, last = 0, time.monotonic()
        while True:
            append_step(w, k)
            k += 1
            if time.monotonic() - last >= 0.2:
                w.flush(journal=journal(k))
                print(f"F {{k}}", flush=True)
                last = time.monotonic()
            time.sleep(0.0005)  # paces the writer (real time: the kills below land at random moments)
        """
    )


def _run_and_kill(path: Path, after_s: float, kill_at_append: int | None = None) -> int:
    """Run the writer script, SIGKILL it `after_s` after it started writing (or let it kill
    itself at an append); returns the steps its last completed flush covered."""
    proc = subprocess.Popen(
        [sys.executable, "-c", _kill_script(path, kill_at_append)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        text=True,
        bufsize=1,
    )
    assert proc.stdout is not None
    assert proc.stdout.readline().strip() == "START"
    if kill_at_append is None:
        # Real time on purpose: a kill at a random moment of the writer's work. The checks
        # adapt to how far it got (n_flushed), so none depends on how fast the machine was.
        time.sleep(after_s)
        proc.send_signal(signal.SIGKILL)
    out = proc.stdout.read()
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    flushed = [
        int(line.split()[1])
        for line in out.splitlines(keepends=True)
        if line.startswith("F ") and line.endswith("\n")
    ]
    return flushed[-1] if flushed else 0


def plain_events(g: h5py.Group) -> dict[str, np.ndarray]:
    """Event columns of an unrecovered take with plain h5py, as docs/take-format.md says: the
    main datasets, continued by the tail slot that starts where they end."""
    cols = {k: g[k][...] for k in "xypt"}
    n = cols["t"].shape[0]
    for slot, (start, rows) in enumerate(g.attrs.get("tail_meta", np.zeros((2, 2), np.int64))):
        if start == n and rows:
            cols = {k: np.concatenate([v, g[f"tail_{k}"][slot, :rows]]) for k, v in cols.items()}
    return cols


def _check_prefix(f: h5py.File, n: int, exp: Expected) -> None:
    """The first n steps are in the file exactly as appended (device time)."""
    ne, nt = n * EV_PER_STEP, 2 * n
    g = f["events/ev0"]
    cols = plain_events(g)
    for col, want in (("x", exp.ev.x), ("y", exp.ev.y), ("t", exp.ev.t)):
        assert cols[col].shape[0] >= ne
        np.testing.assert_array_equal(cols[col][:ne], want[:ne])
    np.testing.assert_array_equal(cols["p"][:ne], (exp.ev.p[:ne] > 0).astype(np.uint8))
    np.testing.assert_array_equal(g["trigger/t_device"][:nt], exp.trig_t[:nt])
    np.testing.assert_array_equal(g["trigger/host_time_ns"][:nt], exp.trig_host[:nt])
    c = f["frames/cam0"]
    np.testing.assert_array_equal(c["t_exposure_start_device_us"][:n], exp.frame_t[:n])
    np.testing.assert_array_equal(c["images"][:n], exp.images[:n])
    np.testing.assert_array_equal(f["trigger/pulses/t_us"][:n], exp.pulse_t[:n])


def _check_recovered(path: Path, n_flushed: int) -> None:
    """A sealed take: valid, readable, at least what was flushed, and exact rig times."""
    assert validate_take(path) == []
    with Take(path) as take:
        assert take.status == "complete"
        assert take.time_domain == "rig"
        assert take.recovered_utc is not None
        rep = take.recovery_report
        assert rep is not None
        assert rep["outcome"] == "sealed"
        n_frames = len(take.frames("cam0"))
        n_ev = take.sensor("ev0").count
        n_pulses = len(take.pulses())
        assert n_frames >= n_flushed
        assert n_pulses >= n_flushed
        assert n_ev >= n_flushed * EV_PER_STEP
        exp = expected(max(n_frames, n_pulses, -(-n_ev // EV_PER_STEP)))
        ev = take.sensor("ev0").events()
        np.testing.assert_array_equal(ev.t, exp.ev.t[:n_ev] - OFF_EV)
        np.testing.assert_array_equal(ev.x, exp.ev.x[:n_ev])
        np.testing.assert_array_equal(ev.p, exp.ev.p[:n_ev])
        fs = take.frames("cam0")
        np.testing.assert_array_equal(fs.timestamps_us, exp.frame_t[:n_frames] - OFF_CAM)
        assert [fs[i].pulse_index for i in (0, n_frames - 1)] == [0, n_frames - 1]
        tr = take.sensor("ev0").triggers
        np.testing.assert_array_equal(tr.t, exp.trig_t[: len(tr)] - OFF_EV)
        np.testing.assert_array_equal(take.pulses().t_us, exp.pulse_t[:n_pulses])
        # Windowed reads work like on any finalized take.
        a = RIG0 + 3 * PERIOD
        win = take.sensor("ev0").events(a, a + PERIOD)
        want = exp.ev.t[:n_ev] - OFF_EV
        np.testing.assert_array_equal(win.t, want[(want >= a) & (want < a + PERIOD)])
        report = take.sync_report
        assert report is not None
        # The journal of the last flush made it into the report (it may be one flush newer).
        jl = [r for r in report.losses if r.reason == "test: queue full"]
        assert len(jl) == 1
        assert jl[0].count >= n_flushed
        assert report.device_counters["ev0"]["delivered"] >= n_flushed * EV_PER_STEP
        assert report.trigger_link == {"corrupt_lines": 1}
        assert any("ended by a crash" in r.reason for r in report.losses)
        assert any("ended by a crash" in w for w in report.warnings)
        assert report.devices["ev0"].residual_max_us < 1.0
        assert report.devices["cam0"].residual_max_us < 1.0


def test_sigkill_at_random_moments_then_recover(tmp_path: Path) -> None:
    """8 writers SIGKILLed at seeded random moments, 3 more killed between two column appends:
    flushed data intact, every take seals."""
    rng = np.random.default_rng(20240611)
    # Column writes per flush: ~14 small series, 4 tail columns, 4 per whole event chunk.
    runs = [(float(t), None) for t in rng.uniform(0.25, 1.2, size=8)]
    runs += [(0.0, int(n)) for n in rng.integers(250, 1200, size=3)]
    for i, (after_s, at_append) in enumerate(runs):
        path = tmp_path / f"kill{i}.h5"
        n_flushed = _run_and_kill(path, after_s, at_append)
        exp = expected(n_flushed)
        with h5py.File(path, "r") as f:  # plain h5py, no h5clear
            assert f.attrs["status"] == "recording"
            assert int(f.attrs["flush_count"]) >= (1 if n_flushed else 0)
            _check_prefix(f, n_flushed, exp)
        with Take(path) as take:  # the reader merges the tail of an unrecovered take
            np.testing.assert_array_equal(take.sensor("ev0").events().t[: n_flushed * EV_PER_STEP], exp.ev.t)
        assert find_unfinished(tmp_path) == [path]
        dry = recover_take(path, dry_run=True)
        rr = recover_take(path)
        assert not find_unfinished(tmp_path)
        assert rr.trims == dry.trims
        if n_flushed < 3:  # killed before pulses reached the file: sealed failed, data kept
            assert rr.outcome == "sealed_failed", rr
            continue
        assert dry.outcome == "would_seal"
        assert rr.outcome == "sealed", rr
        assert rr.sealed
        assert rr.flush_interval_s == pytest.approx(0.2)
        assert rr.frames["cam0"] >= n_flushed
        _check_recovered(path, n_flushed)
        assert recover_take(path).outcome == "not_needed"


# -- finalize interrupted ------------------------------------------------------------------
N_STEPS = 120
MAPS = {"cam0": ClockMap(OFF_CAM, 0), "ev0": ClockMap(OFF_EV, 0)}


def _report(n: int) -> SyncReport:
    return SyncReport(
        rate_hz=1e6 / PERIOD, n_pulses=n, t_first_pulse_us=RIG0, t_last_pulse_us=RIG0 + (n - 1) * PERIOD
    )


def _unfinished(path: Path, n: int = N_STEPS) -> Path:
    w = open_writer(path)
    for k in range(n):
        append_step(w, k)
    w.flush(journal=journal(n))
    w.close()
    return path


def _finalized_arrays(path: Path) -> dict[str, np.ndarray]:
    with h5py.File(path, "r") as f:
        out = {
            k: f[k][...]
            for k in (
                "events/ev0/t",
                "events/ev0/ms_to_idx",
                "events/ev0/t_offset",
                "events/ev0/trigger/t",
                "frames/cam0/t_exposure_start_us",
                "frames/cam0/pulse_index",
            )
        }
        assert f.attrs["status"] == "complete"
        for attr in (Root.FINALIZE_PLAN, "finalize_started_utc"):
            assert attr not in f.attrs
        assert "t_rig_upto" not in f["events/ev0"].attrs
        assert "finalize_scratch" not in f["events/ev0"]
        return out


class SimulatedCrashError(Exception):
    pass


@pytest.fixture
def small_blocks(monkeypatch: pytest.MonkeyPatch) -> None:
    # Many finalize blocks from a small take: 2048 events per block.
    monkeypatch.setattr(finalize_mod, "_FINALIZE_BLOCK", 2 * CHUNK)


@pytest.mark.parametrize("stage", ["scratch_written", "scratch_logged", "t_written"])
@pytest.mark.usefixtures("small_blocks")
def test_crash_mid_finalize_resumes_exactly(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, stage: str
) -> None:
    ref = _unfinished(tmp_path / "ref.h5")
    crash = tmp_path / "crash.h5"
    shutil.copy(ref, crash)
    with TakeWriter.resume(ref, WRITER_CFG) as w:
        w.finalize(MAPS, {"cam0": np.arange(N_STEPS)}, _report(N_STEPS))
    want = _finalized_arrays(ref)

    calls = {"n": 0}

    def crash_at(s: str, sensor: str, start: int) -> None:
        if s == stage:
            calls["n"] += 1
            if calls["n"] == 7:  # in the middle of the take (36000 events, 18 blocks)
                raise SimulatedCrashError(f"{s} at {start}")

    monkeypatch.setattr(finalize_mod, "_crash_point", crash_at)
    w = TakeWriter.resume(crash, WRITER_CFG)
    with pytest.raises(SimulatedCrashError):
        w.finalize(MAPS, {"cam0": np.arange(N_STEPS)}, _report(N_STEPS))
    with pytest.raises(TakeError, match="no more data"):
        append_step(w, N_STEPS)
    w.close()  # flushes whatever was in memory: the worst case for double mapping
    monkeypatch.setattr(finalize_mod, "_crash_point", lambda *a: None)
    assert find_unfinished(tmp_path) == [crash]
    assert any("finalize was interrupted" in p for p in validate_take(crash))
    with TakeWriter.resume(crash, WRITER_CFG) as w:
        assert w.finalize_pending
        assert w.repairs == []
        with pytest.raises(TakeError, match="continue_finalize"):
            w.finalize(MAPS, {"cam0": np.arange(N_STEPS)}, _report(N_STEPS))
        w.continue_finalize()
        assert w.status == "complete"
    got = _finalized_arrays(crash)
    for key, arr in want.items():
        np.testing.assert_array_equal(got[key], arr, err_msg=key)
    assert validate_take(crash) == []


@pytest.mark.usefixtures("small_blocks")
def test_sigkill_mid_finalize_then_recover(tmp_path: Path) -> None:
    """A real kill between writing a block and confirming it; recover_take finishes exactly."""
    ref = _unfinished(tmp_path / "ref.h5")
    crash = tmp_path / "crash.h5"
    shutil.copy(ref, crash)
    with TakeWriter.resume(ref, WRITER_CFG) as w:
        w.finalize(MAPS, {"cam0": np.arange(N_STEPS)}, _report(N_STEPS))
    want = _finalized_arrays(ref)
    script = textwrap.dedent(
        f"""
        import os, signal
        import numpy as np
        from pathlib import Path
        import rigd.take.finalize as fm
        import rigd.take.writer as wm
        from tests.rigd.test_take_recover import MAPS, N_STEPS, WRITER_CFG, CHUNK, _report
        fm._FINALIZE_BLOCK = 2 * CHUNK
        seen = []
        def kill(stage, sensor, start):
            if stage == "t_written":
                seen.append(start)
                if len(seen) == 5:
                    os.kill(os.getpid(), signal.SIGKILL)
        fm._crash_point = kill
        w = wm.TakeWriter.resume(Path({str(crash)!r}), WRITER_CFG)
        w.finalize(MAPS, {{"cam0": np.arange(N_STEPS)}}, _report(N_STEPS))
        """
    )
    proc = subprocess.run([sys.executable, "-c", script], cwd=ROOT, check=False)
    assert proc.returncode == -signal.SIGKILL
    with h5py.File(crash, "r") as f:
        assert Root.FINALIZE_PLAN in f.attrs
        assert 0 < int(f["events/ev0"].attrs["t_rig_upto"]) < N_STEPS * EV_PER_STEP
    assert recover_take(crash, dry_run=True).outcome == "would_seal"
    rr = recover_take(crash)
    assert rr.outcome == "sealed"
    assert rr.finalize_resumed
    got = _finalized_arrays(crash)
    for key, arr in want.items():
        np.testing.assert_array_equal(got[key], arr, err_msg=key)
    assert validate_take(crash) == []
    with open_take(crash) as take:
        assert take.summary().recovered_utc is not None
        report = take.sync_report
        assert report is not None
        assert any("finalize was interrupted" in w for w in report.warnings)


# -- repair ----------------------------------------------------------------------------------
def _damage(f: h5py.File) -> None:
    """What a kill inside a flush can leave: columns of unequal length, chunks never written,
    a zero-filled tail, preallocated images."""
    g = f["events/ev0"]
    n = g["t"].shape[0]
    g["x"].resize((n + 5,))  # the kill came between column appends
    g["x"][n:] = 1
    for col in ("y", "p"):
        g[col].resize((n + 2 * CHUNK,))
        g[col][n:] = 1
    g["t"].resize((n + 2 * CHUNK,))  # extent ahead of its chunks: would read as zeros
    g["trigger/host_time_ns"].resize((g["trigger/t"].shape[0] - 3,))
    c = f["frames/cam0"]
    nf = c["images"].shape[0]
    c["images"].resize((nf + 64, *CAM_SHAPE))  # preallocated, never written
    c["images"][nf] = 9  # one frame stored whose timestamps were not
    for k in ("t_exposure_start_us", "t_exposure_start_device_us", "exposure_us", "frame_counter"):
        c[k].resize((nf + 1,))
    f["trigger/pulses/t_us"].resize((f["trigger/pulses/t_us"].shape[0] + 1,))


def test_repair_trims_and_reports_everything(tmp_path: Path) -> None:
    path = _unfinished(tmp_path / "d.h5", n=40)
    with h5py.File(path, "r+") as f:
        _damage(f)
    before = path.read_bytes()
    dry = recover_take(path, dry_run=True)
    assert path.read_bytes() == before  # a dry run changes nothing
    by_path = {t.hpath: t for t in dry.trims}
    assert set(by_path) == {"/events/ev0", "/events/ev0/trigger", "/frames/cam0", "/trigger/pulses"}
    ev = by_path["/events/ev0"]
    assert ev.after == 40 * EV_PER_STEP
    assert "unequal length" in ev.reason
    assert "never reached the file" in ev.reason
    assert ev.lost == 2 * CHUNK
    assert by_path["/events/ev0/trigger"].after == 80 - 3
    cam = by_path["/frames/cam0"]
    assert cam.after == 40
    assert cam.lengths_before["images"] == 40 + 64
    assert cam.lost == 1  # the stored image; the 63 preallocated frames are not data
    assert by_path["/trigger/pulses"].after == 40
    rr = recover_take(path)
    assert rr.outcome == "sealed"
    assert rr.trims == dry.trims
    lost = {(r.device, r.what): r.count for r in rr.losses_added if r.count}
    assert lost == {
        ("ev0", "events"): 2 * CHUNK,
        ("ev0", "triggers"): 3,
        ("cam0", "frames"): 1,
        ("trigger", "pulses"): 1,
    }
    assert validate_take(path) == []
    with Take(path) as take:
        assert take.sensor("ev0").count == 40 * EV_PER_STEP
        assert len(take.sensor("ev0").triggers) == 77
        assert len(take.frames("cam0")) == 40
        report = take.sync_report
        assert report is not None
        assert (
            sum(r.count for r in report.losses if r.reason.startswith("cut by crash recovery"))
            == 2 * CHUNK + 5
        )


def test_non_monotonic_tail_is_dropped(tmp_path: Path) -> None:
    path = _unfinished(tmp_path / "m.h5", n=20)
    with h5py.File(path, "r+") as f:
        t = f["events/ev0/t"]
        t[-50:] = 0  # a zero-filled tail chunk the flush did not finish
    with TakeWriter.resume(path, WRITER_CFG) as w:
        (trim,) = w.repairs
        assert trim.hpath == "/events/ev0"
        assert trim.after == 20 * EV_PER_STEP - 50
        assert "decreases at index" in trim.reason
        assert w.stats["ev0"].items == 20 * EV_PER_STEP - 50


def test_no_pulses_seals_failed_and_keeps_data(tmp_path: Path) -> None:
    path = tmp_path / "np.h5"
    w = open_writer(path)
    for k in range(10):
        s = step(k)
        w.append_frame("cam0", s.frame)
        w.append_events("ev0", s.events)
    w.flush()
    w.close()
    rr = recover_take(path)
    assert rr.outcome == "sealed_failed"
    assert rr.sealed
    assert rr.reason is not None
    assert "no trigger pulse" in rr.reason
    assert validate_take(path) == []
    with Take(path) as take:
        assert take.status == "failed"
        assert take.time_domain == "device"
        assert take.summary().failure_reason is not None
        assert take.recovery_report is not None
        np.testing.assert_array_equal(take.sensor("ev0").events().t, expected(10).ev.t)
    assert find_unfinished(tmp_path) == []
    assert recover_take(path).outcome == "not_needed"


def test_truncated_failed_take_is_repaired_and_sealed(tmp_path: Path) -> None:
    """A take its writer marked failed (disk full), then cut short: recovery makes it open and
    seals what was flushed into rig time, keeping the failure reason."""
    path = _unfinished(tmp_path / "tf.h5", n=40)
    size = path.stat().st_size
    with h5py.File(path, "r+") as f:
        f.attrs["status"] = "failed"
        f.attrs["failure_reason"] = "disk full"
        f["late_write"] = np.arange(4096)  # the write the disk had no room for
    grown = path.stat().st_size
    assert grown > size
    os.truncate(path, grown - 1)  # the last write never made it
    with pytest.raises(TakeError, match="truncated file"):
        open_take(path)
    assert find_unfinished(tmp_path) == [path]
    rr = recover_take(path)
    assert rr.outcome == "sealed", rr
    assert rr.status_after == "complete"
    assert rr.events == {"ev0": 40 * EV_PER_STEP}
    assert validate_take(path) == []
    with Take(path) as take:
        assert take.status == "complete"
        assert take.time_domain == "rig"
        assert take.summary().failure_reason == "disk full"
        np.testing.assert_array_equal(take.sensor("ev0").events().t, expected(40).ev.t - OFF_EV)
    assert find_unfinished(tmp_path) == []


# -- schema 1.0, journal, host times -------------------------------------------------------
def _as_schema_1_0(path: Path) -> None:
    """What a 1.0 writer produced: no trigger host times, no flush bookkeeping."""
    with h5py.File(path, "r+") as f:
        f.attrs["schema_version"] = "1.0"
        del f["events/ev0/trigger/host_time_ns"]
        for attr in ("flush_count", "last_flush_utc", "flush_interval_s"):
            if attr in f.attrs:
                del f.attrs[attr]
        if "journal_json" in f:
            del f["journal_json"]


def test_schema_1_0_takes_still_read_validate_and_recover(tmp_path: Path) -> None:
    done = _unfinished(tmp_path / "done.h5", n=30)
    with TakeWriter.resume(done, WRITER_CFG) as w:
        w.finalize(MAPS, {"cam0": np.arange(30)}, _report(30))
    _as_schema_1_0(done)
    assert validate_take(done) == []
    with open_take(done) as take:
        assert take.schema_version == "1.0"
        assert take.journal is None
        np.testing.assert_array_equal(take.sensor("ev0").trigger_host_times, np.full(60, -1))
        np.testing.assert_array_equal(take.sensor("ev0").triggers.t, expected(30).trig_t - OFF_EV)
    rec = _unfinished(tmp_path / "rec.h5", n=30)
    _as_schema_1_0(rec)
    assert validate_take(rec) == []
    rr = recover_take(rec)
    assert rr.outcome == "sealed", rr
    assert any("without a recorded host time" in w for w in rr.warnings)
    assert validate_take(rec) == []
    with open_take(rec) as take:
        assert take.schema_version == "1.0"  # a resumed take keeps its version
        np.testing.assert_array_equal(take.sensor("ev0").events().t, expected(30).ev.t - OFF_EV)
    # A 1.1 take must have the dataset.
    bad = _unfinished(tmp_path / "bad.h5", n=3)
    with h5py.File(bad, "r+") as f:
        del f["events/ev0/trigger/host_time_ns"]
    assert any("/events/ev0/trigger/host_time_ns" in p and "missing" in p for p in validate_take(bad))


def test_journal_flush_bookkeeping_and_host_times(tmp_path: Path) -> None:
    path = tmp_path / "j.h5"
    w = open_writer(path, flush_interval_s=0.5)
    append_step(w, 0)
    w.append_triggers(
        "ev0", TriggerEvents(np.array([10**9], np.int64), np.ones(1, np.uint8), np.zeros(1, np.uint8))
    )
    w.flush(journal=journal(1))
    w.flush(journal={"losses": [], "warnings": ["second"]})
    w.flush()  # no journal: the last one stays
    with pytest.raises(TakeError, match="not JSON-serialisable"):
        w.flush(journal={"bad": object()})
    w.close()
    with h5py.File(path, "r") as f:
        assert f.attrs["flush_interval_s"] == 0.5
        assert int(f.attrs["flush_count"]) == 3
        assert "T" in str(f.attrs["last_flush_utc"])
    with open_take(path) as take:
        assert take.journal == {"losses": [], "warnings": ["second"]}
        np.testing.assert_array_equal(
            take.sensor("ev0").trigger_host_times, [step(0).packet_host_ns] * 2 + [-1]
        )
    with pytest.raises(TakeError, match="flush_interval_s"):
        TakeWriter(
            tmp_path / "z.h5",
            rig_config_json="{}",
            take_id="z",
            config=WRITER_CFG,
            rigd_version="t",
            flush_interval_s=0,
        )


# -- refusing ------------------------------------------------------------------------------
@pytest.fixture
def live_writer(tmp_path: Path) -> Iterator[Path]:
    path = tmp_path / "live.h5"
    script = textwrap.dedent(
        f"""
        import threading
        from pathlib import Path
        from tests.rigd.test_take_recover import append_step, open_writer
        w = open_writer(Path({str(path)!r}))
        for k in range(5):
            append_step(w, k)
        w.flush()
        print("ready", flush=True)
        threading.Event().wait()  # hold the take open until killed, however long the test takes
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "ready"
        yield path
    finally:
        proc.kill()
        proc.wait()


def test_locked_take_is_in_use_and_untouched(live_writer: Path) -> None:
    before = live_writer.read_bytes()
    for dry in (True, False):
        rr = recover_take(live_writer, dry_run=dry)
        assert rr.outcome == "in_use"
        assert not rr.sealed
        assert rr.reason is not None
        assert str(live_writer) in rr.reason
    assert live_writer.read_bytes() == before
    assert find_unfinished(live_writer.parent) == [live_writer]
    with pytest.raises(TakeError, match="in use"):
        TakeWriter.resume(live_writer, WRITER_CFG)


def test_damaged_files_give_clear_errors(tmp_path: Path) -> None:
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"not an hdf5 file" * 64)
    with pytest.raises(TakeFormatError, match=r"junk\.h5: cannot be opened as an HDF5 file"):
        recover_take(junk)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = [1]
    with pytest.raises(TakeFormatError, match=r"other\.h5: /: attr schema"):
        recover_take(other)
    with pytest.raises(TakeError, match=r"missing\.h5: no such take file"):
        recover_take(tmp_path / "missing.h5")
    gone = _unfinished(tmp_path / "gone.h5", n=3)
    with h5py.File(gone, "r+") as f:
        del f["frames/cam0/host_time_ns"]
    with pytest.raises(TakeFormatError, match=r"gone\.h5: /frames/cam0/host_time_ns is missing"):
        recover_take(gone)
    assert find_unfinished(tmp_path) == [gone]  # junk and non-takes are skipped


# -- the command -----------------------------------------------------------------------------
def _app() -> typer.Typer:
    app = typer.Typer()
    app.command()(recover_command)

    @app.command("other")
    def _other() -> None:  # two commands keep typer from collapsing the app into one
        pass

    return app


def test_recover_command(tmp_path: Path) -> None:
    takes = tmp_path / "takes"
    takes.mkdir()
    a = _unfinished(takes / "a.h5", n=12)
    runner = CliRunner()
    res = runner.invoke(_app(), ["recover-command", str(takes), "--dry-run"])
    assert res.exit_code == 0, res.output
    assert "WOULD_SEAL" in res.output
    assert "a.h5" in res.output
    res = runner.invoke(_app(), ["recover-command", str(takes), "--json"])
    assert res.exit_code == 0, res.output
    (out,) = json.loads(res.stdout)  # stdout only: log lines go to stderr
    assert out["outcome"] == "sealed"
    assert out["frames"] == {"cam0": 12}
    res = runner.invoke(_app(), ["recover-command", str(takes)])
    assert res.exit_code == 0
    assert "no unfinished takes" in res.output
    res = runner.invoke(_app(), ["recover-command", str(a)])
    assert res.exit_code == 0
    assert "nothing to recover" in res.output
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"x" * 100)
    res = runner.invoke(_app(), ["recover-command", str(a), str(junk)])
    assert res.exit_code == 1
    assert "ERROR" in res.output
    assert "junk.h5" in res.output


@pytest.mark.parametrize("then", ["abandon", "fail_and_close"])
def test_disk_full_truncated_take_is_extended_and_sealed(tmp_path: Path, then: str) -> None:
    """A write that fails for lack of space leaves the file shorter than its header says; HDF5
    refuses to open it. Recovery reads it through a zero-padded view (dry run) or extends it
    with a hole, and keeps everything flushed before the failure. A writer that then tries to
    mark the take failed and closes it gets OSError (not HDF5's RuntimeError), the file is left
    as the failure left it (and unlocked), and the process survives."""
    path = tmp_path / "full.h5"
    script = textwrap.dedent(
        f"""
        import os, resource, signal, sys
        from pathlib import Path
        from tests.rigd.test_take_recover import append_step, journal, open_writer
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # writes past the limit fail with EFBIG
        w = open_writer(Path({str(path)!r}))
        resource.setrlimit(resource.RLIMIT_FSIZE, (2_000_000, 2_000_000))
        k = 0
        try:
            while True:
                append_step(w, k)
                k += 1
                if k % 50 == 0:
                    w.flush(journal=journal(k))
                    print(f"F {{k}}", flush=True)
        except OSError as exc:
            print("E", exc.errno, flush=True)
        if {then!r} == "fail_and_close":
            for call in (lambda: w.fail("disk full"), w.close):
                try:
                    call()
                except OSError as exc:
                    print("C", exc.errno, flush=True)
            import gc
            gc.collect()  # freeing the objects of a file HDF5 could not close must not crash
            print("survived", flush=True)
        os._exit(0)
        """
    )
    proc = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, check=False
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = proc.stdout.splitlines()
    assert "E 27" in lines  # EFBIG, raised as OSError
    n_flushed = max(int(line.split()[1]) for line in lines if line.startswith("F "))
    if then == "fail_and_close":
        assert lines[-3:] == ["C 27", "C 27", "survived"]
        if recover_take(path, dry_run=True).status_before == "failed":
            # "failed" reached the file before the writes ran out of room: repaired and sealed
            # with the reason kept (test_truncated_failed_take_is_repaired_and_sealed).
            assert recover_take(path).outcome == "sealed"
            assert validate_take(path) == []
            with Take(path) as take:
                assert take.status == "complete"
                assert take.summary().failure_reason == "disk full"
                np.testing.assert_array_equal(
                    take.sensor("ev0").events().t[: n_flushed * EV_PER_STEP],
                    expected(n_flushed).ev.t - OFF_EV,
                )
            return
    with pytest.raises(TakeFormatError, match=r"truncated by a failed write"):
        TakeWriter.resume(path, WRITER_CFG)
    assert find_unfinished(tmp_path) == [path]
    before = path.read_bytes()
    dry = recover_take(path, dry_run=True)
    assert path.read_bytes() == before
    assert dry.truncated_bytes > 0
    assert dry.outcome == "would_seal"
    rr = recover_take(path)
    assert rr.outcome == "sealed", rr
    assert rr.truncated_bytes == dry.truncated_bytes
    assert rr.trims == dry.trims
    assert any("short of what its header records" in w for w in rr.warnings)
    _check_recovered(path, n_flushed)
    with h5py.File(path, "r") as f:
        assert "truncated_eof" not in f.attrs


def test_stale_chunk_tails_are_trimmed(tmp_path: Path) -> None:
    """A chunk the interrupted flush did not update reads as its old rows plus zeros while the
    extent covers the new rows: seen by device times and host times that drop to 0, and by t
    no longer equal to t_device."""
    path = _unfinished(tmp_path / "s.h5", n=30)
    with h5py.File(path, "r+") as f:
        tg = f["events/ev0/trigger"]
        for k in tg:  # 6 rows more, inside the existing chunk: zeros
            tg[k].resize((66,))
        tg["t"][60:] = 123  # t was updated, its copy t_device was not
        c = f["frames/cam0"]
        for k in c:
            c[k].resize((33, *c[k].shape[1:]))
        c["host_time_ns"][30:] = 5  # only host times made it
        c["exposure_us"][30:] = 5000
        pulses = f["trigger/pulses"]
        for k in pulses:
            pulses[k].resize((32,))
    with TakeWriter.resume(path, WRITER_CFG) as w:
        by_path = {t.hpath: t for t in w.repairs}
    assert {k: (t.after, t.lost) for k, t in by_path.items()} == {
        "/events/ev0/trigger": (60, 6),
        "/frames/cam0": (30, 3),
        "/trigger/pulses": (30, 2),
    }
    assert all("zero-filled tail" in t.reason for t in by_path.values())
    # A column that is zero everywhere carries no information and never trims anything.
    p2 = tmp_path / "nohost.h5"
    w2 = open_writer(p2)
    for k in range(5):
        s = step(k)
        w2.append_frame("cam0", Frame(s.frame.image, s.frame.t_exposure_start_us, 5000, k, 0))
        w2.append_pulses(s.pulse)
    w2.close()
    with TakeWriter.resume(p2, WRITER_CFG) as w:
        assert w.repairs == []
