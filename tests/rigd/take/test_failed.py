"""Takes their own writer marked `failed` before finalize (disk full, a fault): recovery seals
what was flushed into rig time and keeps the failure reason."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from rigd.app.testing.crash import (
    EV_PER_STEP,
    OFF_CAM,
    OFF_EV,
    append_step,
    expected,
    journal,
    open_writer,
    step,
)
from rigd.core.errors import TakeFormatError
from rigd.take import Take, find_unfinished, recover_take, validate_take
from rigd.take.recover import needs_recovery
from rigd.take.seal import fail_take


def _failed(path: Path, n: int = 30, *, pulses: bool = True, events: bool = True) -> Path:
    w = open_writer(path)
    for k in range(n):
        if pulses and events:
            append_step(w, k)
        else:
            s = step(k)
            w.append_frame("cam0", s.frame)
            if pulses:
                w.append_pulses(s.pulse)
        if k % 10 == 9:
            w.flush(journal=journal(k))
    fail_take(w, "disk full")
    w.close()
    return path


def test_failed_take_is_sealed_with_its_reason(tmp_path: Path) -> None:
    path = _failed(tmp_path / "f.h5")
    assert needs_recovery(path)
    assert find_unfinished(tmp_path) == [path]
    before = path.read_bytes()
    dry = recover_take(path, dry_run=True)
    assert dry.outcome == "would_seal"
    assert path.read_bytes() == before
    rr = recover_take(path)
    assert rr.outcome == "sealed", rr
    assert rr.status_before == "failed"
    assert rr.status_after == "complete"
    assert rr.failure_reason_before == "disk full"
    assert "disk full" in rr.line()
    assert validate_take(path) == []
    with Take(path) as take:
        assert take.status == "complete"
        assert take.time_domain == "rig"
        s = take.summary()
        assert s.failure_reason == "disk full"
        assert s.recovered_utc is not None
        assert any("marked failed by its writer (disk full)" in w for w in s.warnings)
        np.testing.assert_array_equal(take.sensor("ev0").events().t, expected(30).ev.t - OFF_EV)
        np.testing.assert_array_equal(take.camera("cam0").timestamps_us, expected(30).frame_t - OFF_CAM)
    assert not needs_recovery(path)
    assert find_unfinished(tmp_path) == []
    assert recover_take(path).outcome == "not_needed"


def test_failed_take_without_pulses_stays_failed_with_both_reasons(tmp_path: Path) -> None:
    path = _failed(tmp_path / "np.h5", pulses=False, events=False)
    assert needs_recovery(path)
    rr = recover_take(path)
    assert rr.outcome == "sealed_failed", rr
    assert validate_take(path) == []
    with Take(path) as take:
        assert take.status == "failed"
        reason = take.summary().failure_reason
        assert reason is not None
        assert reason.startswith("disk full; ")
        assert "no trigger pulse" in reason
        assert take.recovered_utc is not None
    assert not needs_recovery(path)
    assert recover_take(path).outcome == "not_needed"


def test_failed_take_with_an_empty_sensor_is_sealed(tmp_path: Path) -> None:
    path = _failed(tmp_path / "e.h5", pulses=True, events=False)
    rr = recover_take(path)
    assert rr.outcome == "sealed", rr
    assert validate_take(path) == []
    with Take(path) as take:
        assert len(take.sensor("ev0").events()) == 0
        assert take.summary().failure_reason == "disk full"
        rep = take.sync_report
        assert rep is not None
        assert "ev0: recorded nothing (0 events, 0 trigger edges)" in rep.warnings


def test_needs_recovery_of_other_files(tmp_path: Path) -> None:
    path = _failed(tmp_path / "c.h5")
    recover_take(path)
    assert not needs_recovery(path)
    rec = tmp_path / "r.h5"
    w = open_writer(rec)
    append_step(w, 0)
    w.close()
    assert needs_recovery(rec)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = np.arange(3)
    with pytest.raises(TakeFormatError, match="not a rigd take"):
        needs_recovery(other)
    assert find_unfinished(tmp_path) == [rec]
    assert EV_PER_STEP > 0
