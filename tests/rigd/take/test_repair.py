"""Recovery repairs what a crash or a full disk left in a take: columns of unequal length,
chunks that never reached the file, zero-filled and stale tails, a file shorter than its header.

The synthetic rig of `test_take_recover` (device time = rig time + a constant), so what
survives is asserted exactly.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest

from rigd.app.testing.crash import (
    CAM_SHAPE,
    CHUNK,
    EV_PER_STEP,
    OFF_EV,
    WRITER_CFG,
    check_recovered,
    expected,
    open_writer,
    step,
)
from rigd.app.testing.crash import (
    unfinished as _unfinished,
)
from rigd.core.errors import TakeError, TakeFormatError
from rigd.core.frames import Frame
from rigd.take import Take, find_unfinished, open_take, recover_take, validate_take
from rigd.take.resume import resume_take

ROOT = Path(__file__).parents[3]


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


@pytest.mark.slow
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
        assert len(take.camera("cam0")) == 40
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
    with resume_take(path, WRITER_CFG) as w:
        (trim,) = w.state.repairs
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


@pytest.mark.slow
@pytest.mark.parametrize("then", ["abandon", "fail_and_close"])
def test_disk_full_truncated_take_is_extended_and_sealed(tmp_path: Path, then: str) -> None:
    """A write that fails for lack of space can leave the file shorter than its header says;
    HDF5 refuses to open it then. Recovery reads it through a zero-padded view (dry run) or
    extends it with a hole, and keeps everything flushed before the failure, truncated or not
    (test_truncated_failed_take_is_repaired_and_sealed makes the truncated case for sure). A
    writer that then tries to mark the take failed and closes it gets OSError (not HDF5's
    RuntimeError) from both, the file is left as the failure left it, and the process
    survives."""
    path = tmp_path / "full.h5"
    script = textwrap.dedent(
        f"""
        import os, resource, signal, sys
        from pathlib import Path
        from rigd.app.testing.crash import append_step, journal, open_writer
        from rigd.take.seal import fail_take
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
            for call in (lambda: fail_take(w, "disk full"), w.close):
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
    assert find_unfinished(tmp_path) == [path]
    before = path.read_bytes()
    dry = recover_take(path, dry_run=True)
    assert path.read_bytes() == before
    assert dry.outcome == "would_seal"
    if dry.truncated_bytes:
        # The header ran ahead of the data (a flush whose data writes failed after it): HDF5
        # refuses the file until recovery extends it.
        with pytest.raises(TakeFormatError, match=r"truncated by a failed write"):
            resume_take(path, WRITER_CFG)
    # Else the failing write was the data's own (the writer keeps no chunk cache, so data goes
    # out at the call, before any flush refers to it): the file is as last flushed, whole.
    rr = recover_take(path)
    assert rr.outcome == "sealed", rr
    assert rr.truncated_bytes == dry.truncated_bytes
    assert rr.trims == dry.trims
    assert any("short of what its header records" in w for w in rr.warnings) == bool(dry.truncated_bytes)
    check_recovered(path, n_flushed)
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
    with resume_take(path, WRITER_CFG) as w:
        by_path = {t.hpath: t for t in w.state.repairs}
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
    with resume_take(p2, WRITER_CFG) as w:
        assert w.state.repairs == []
