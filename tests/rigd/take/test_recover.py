"""Crash safety: SIGKILLed writers leave takes that open, keep every flushed item, and seal.

The synthetic rig has an exactly known clock relation (device time = rig time + a constant
per device; pulses every PERIOD us; the event sensor's trigger-in edges at the pulses), so
the rig times of a recovered take can be asserted exactly.
"""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np
import pytest
import typer
from typer.testing import CliRunner

import rigd.take.finalize as finalize_mod
from rigd.app.commands.recover import recover_command
from rigd.app.testing.crash import (
    CHUNK,
    EV_PER_STEP,
    MAPS,
    N_STEPS,
    OFF_EV,
    WRITER_CFG,
    Expected,
    append_step,
    check_recovered,
    expected,
    journal,
    open_writer,
    step,
)
from rigd.app.testing.crash import (
    report as _report,
)
from rigd.app.testing.crash import (
    unfinished as _unfinished,
)
from rigd.core.errors import TakeError, TakeFormatError
from rigd.core.events import TriggerEvents
from rigd.core.layout import Root
from rigd.take import Take, TakeWriter, find_unfinished, open_take, recover_take, validate_take
from rigd.take.resume import resume_take
from rigd.take.seal import continue_finalize, finalize_take

ROOT = Path(__file__).parents[3]


def _kill_script(path: Path, kill_at_append: int | None = None) -> str:
    """The writer loop; with kill_at_append it SIGKILLs itself at that column write (between
    the column appends of one flush, the moment a timed kill rarely hits)."""
    return textwrap.dedent(
        f"""
        import os, signal, sys, time
        from pathlib import Path
        import rigd.take.sinks as sinks
        from rigd.app.testing.crash import append_step, journal, open_writer
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


@pytest.mark.slow
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
        check_recovered(path, n_flushed)
        assert recover_take(path).outcome == "not_needed"


# -- finalize interrupted ------------------------------------------------------------------
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


@pytest.mark.slow
@pytest.mark.parametrize("stage", ["scratch_written", "scratch_logged", "t_written"])
@pytest.mark.usefixtures("small_blocks")
def test_crash_mid_finalize_resumes_exactly(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, stage: str
) -> None:
    ref = _unfinished(tmp_path / "ref.h5")
    crash = tmp_path / "crash.h5"
    shutil.copy(ref, crash)
    with resume_take(ref, WRITER_CFG) as w:
        finalize_take(w, MAPS, {"cam0": np.arange(N_STEPS)}, _report(N_STEPS))
    want = _finalized_arrays(ref)

    calls = {"n": 0}

    def crash_at(s: str, sensor: str, start: int) -> None:
        if s == stage:
            calls["n"] += 1
            if calls["n"] == 7:  # in the middle of the take (36000 events, 18 blocks)
                raise SimulatedCrashError(f"{s} at {start}")

    monkeypatch.setattr(finalize_mod, "_crash_point", crash_at)
    w = resume_take(crash, WRITER_CFG)
    with pytest.raises(SimulatedCrashError):
        finalize_take(w, MAPS, {"cam0": np.arange(N_STEPS)}, _report(N_STEPS))
    with pytest.raises(TakeError, match="no more data"):
        append_step(w, N_STEPS)
    w.close()  # flushes whatever was in memory: the worst case for double mapping
    monkeypatch.setattr(finalize_mod, "_crash_point", lambda *a: None)
    assert find_unfinished(tmp_path) == [crash]
    assert any("finalize was interrupted" in p for p in validate_take(crash))
    with resume_take(crash, WRITER_CFG) as w:
        assert w.state.finalize_pending
        assert w.state.repairs == []
        with pytest.raises(TakeError, match="continue_finalize"):
            finalize_take(w, MAPS, {"cam0": np.arange(N_STEPS)}, _report(N_STEPS))
        continue_finalize(w)
        assert w.status == "complete"
    got = _finalized_arrays(crash)
    for key, arr in want.items():
        np.testing.assert_array_equal(got[key], arr, err_msg=key)
    assert validate_take(crash) == []


@pytest.mark.slow
@pytest.mark.usefixtures("small_blocks")
def test_sigkill_mid_finalize_then_recover(tmp_path: Path) -> None:
    """A real kill between writing a block and confirming it; recover_take finishes exactly."""
    ref = _unfinished(tmp_path / "ref.h5")
    crash = tmp_path / "crash.h5"
    shutil.copy(ref, crash)
    with resume_take(ref, WRITER_CFG) as w:
        finalize_take(w, MAPS, {"cam0": np.arange(N_STEPS)}, _report(N_STEPS))
    want = _finalized_arrays(ref)
    script = textwrap.dedent(
        f"""
        import os, signal
        import numpy as np
        from pathlib import Path
        import rigd.take.finalize as fm
        from rigd.take.resume import resume_take
        from rigd.take.seal import finalize_take
        from rigd.app.testing.crash import MAPS, N_STEPS, WRITER_CFG, CHUNK, report as _report
        fm._FINALIZE_BLOCK = 2 * CHUNK
        seen = []
        def kill(stage, sensor, start):
            if stage == "t_written":
                seen.append(start)
                if len(seen) == 5:
                    os.kill(os.getpid(), signal.SIGKILL)
        fm._crash_point = kill
        w = resume_take(Path({str(crash)!r}), WRITER_CFG)
        finalize_take(w, MAPS, {{"cam0": np.arange(N_STEPS)}}, _report(N_STEPS))
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
    with resume_take(done, WRITER_CFG) as w:
        finalize_take(w, MAPS, {"cam0": np.arange(30)}, _report(30))
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
        from rigd.app.testing.crash import append_step, open_writer
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


@pytest.mark.slow
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
        resume_take(live_writer, WRITER_CFG)


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
