"""The take verdict: a sealed take that lost anything is `degraded`, with one reason per loss, in
every summary (inspect human and JSON, the console's take list) and `--strict` exits non-zero."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import h5py
import pytest
from typer.testing import CliRunner

from firmware_sim.testing.takes import make_take
from rigd.app.cli import app
from rigd.app.commands.service import take_summary_line, verdict_text
from rigd.app.commands.summaries import STRICT_EXIT
from rigd.app.console.takes import TakeList
from rigd.app.testing.daemon import RunningDaemon
from rigd.core.schema import DeviceSync, LossRecord, SyncReport
from rigd.products.inspect import summarize
from rigd.take.verdict import TakeVerdict, take_verdict

FRAMES = {"cam0": 90}
EVENTS = {"ev0": 1_000_000}


def _report(**kw: object) -> SyncReport:
    return SyncReport.model_validate(
        {"rate_hz": 30.0, "n_pulses": 90, "t_first_pulse_us": 0, "t_last_pulse_us": 2_966_637, **kw}
    )


def _dev(name: str, kind: str, **kw: object) -> DeviceSync:
    base = {
        "device": name,
        "kind": kind,
        "device_ref_us": 0,
        "rig_ref_us": 0,
        "rate": 1.0,
        "drift_ppm": 0.0,
        "n_matched": 90,
        "residual_rms_us": 1.0,
        "residual_max_us": 2.0,
    }
    return DeviceSync.model_validate({**base, **kw})


def _verdict(report: SyncReport | None, **kw: object) -> TakeVerdict:
    frames = kw.pop("frames", FRAMES)
    events = kw.pop("events", EVENTS)
    return take_verdict(str(kw.pop("status", "complete")), report, frames, events, **kw)  # type: ignore[arg-type]


def test_a_take_that_kept_everything_is_complete() -> None:
    v = _verdict(_report(devices={"cam0": _dev("cam0", "rgb_camera"), "ev0": _dev("ev0", "event_sensor")}))
    assert v.verdict == "complete"
    assert v.ok
    assert v.reasons == []
    assert v.line() == "complete — nothing lost"


@pytest.mark.parametrize(
    ("report_fields", "frames", "events", "expected"),
    [
        (
            {"losses": [LossRecord(device="ev0", what="events", count=1234, reason="host buffer full")]},
            FRAMES,
            EVENTS,
            "ev0: 1,234 events lost",
        ),
        (
            {
                "losses": [
                    LossRecord(device="ev1", what="events", count=0, reason="the simulator fell behind"),
                    LossRecord(device="ev1", what="events", count=0, reason="did not deliver up to the end"),
                ]
            },
            FRAMES,
            EVENTS,
            "ev1: events lost (count unknown) (2 loss records)",
        ),
        (
            {
                "losses": [
                    LossRecord(device="cam1", what="frames", count=3, reason="queue full"),
                    LossRecord(device="cam1", what="frames", count=0, reason="device away"),
                ]
            },
            FRAMES,
            EVENTS,
            "cam1: 3 frames and more (count partly unknown) lost (2 loss records)",
        ),
        (
            {"devices": {"ev0": _dev("ev0", "event_sensor", missing_pulses=list(range(45)))}},
            FRAMES,
            EVENTS,
            "ev0: 45 of 90 pulses missing",
        ),
        (
            {"devices": {"cam0": _dev("cam0", "rgb_camera", dropped_frames=[7])}},
            FRAMES,
            EVENTS,
            "cam0: 1 frame dropped",
        ),
        (
            {"pulses_missing_from_box_log": [3, 4]},
            FRAMES,
            EVENTS,
            "trigger: 2 pulses missing from the box's log",
        ),
        ({}, {"cam0": 0}, EVENTS, "cam0: recorded no frames"),
        ({}, FRAMES, {"ev0": 0}, "ev0: recorded no events"),
    ],
    ids=[
        "loss-record",
        "loss-count-unknown",
        "loss-partly-unknown",
        "missing-pulses",
        "dropped-frames",
        "box-log",
        "silent-camera",
        "silent-sensor",
    ],
)
def test_each_kind_of_loss_makes_a_take_degraded(
    report_fields: dict[str, object], frames: dict[str, int], events: dict[str, int], expected: str
) -> None:
    v = _verdict(_report(**report_fields), frames=frames, events=events)
    assert v.verdict == "degraded"
    assert not v.ok
    assert v.reasons == [expected]
    assert v.line().startswith("degraded — " + expected)


def test_a_recovered_take_lost_what_came_after_its_last_flush() -> None:
    v = _verdict(_report(), recovered_utc="2026-11-26T10:00:00Z")
    assert v.verdict == "degraded"
    assert "recovered after a crash" in v.reasons[0]
    v = _verdict(_report(), recovered_utc="2026-11-26T10:00:00Z", failure_reason="disk full")
    assert "after its writer failed it (disk full)" in v.reasons[0]


def test_status_decides_before_losses() -> None:
    assert _verdict(None, status="recording").verdict == "unfinished"
    failed = _verdict(None, status="failed", failure_reason="disk full")
    assert (failed.verdict, failed.reasons) == ("failed", ["disk full"])
    # A complete take without a report cannot say it lost nothing.
    assert _verdict(None).verdict == "degraded"


def test_the_line_names_the_first_reasons_and_counts_the_rest() -> None:
    v = TakeVerdict(verdict="degraded", reasons=[f"r{i}" for i in range(6)])
    assert v.line() == "degraded — r0; r1; r2; r3 (+2 more)"


def _with_report(src: Path, dst: Path, **changes: object) -> Path:
    """A copy of a finalized take whose stored sync report has `changes` (as a capture that lost
    data would have written it)."""
    shutil.copy(src, dst)
    with h5py.File(dst, "r+") as f:
        report = json.loads(f["sync/report_json"][()])
        report.update(changes)
        del f["sync/report_json"]
        f["sync/report_json"] = json.dumps(report)
    return dst


@pytest.fixture(scope="module")
def clean_take(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_take(tmp_path_factory.mktemp("verdict") / "clean.h5").path


@pytest.mark.slow
def test_inspect_shows_the_verdict_first_and_strict_exits_on_a_degraded_take(
    clean_take: Path, tmp_path: Path
) -> None:
    runner = CliRunner()
    ok = runner.invoke(app, ["inspect", str(clean_take), "--strict"])
    assert ok.exit_code == 0, ok.output
    assert ok.stdout.splitlines()[0] == "verdict: complete — nothing lost"

    lost = LossRecord(device="ev0", what="events", count=500, reason="host buffer full").model_dump()
    bad = _with_report(clean_take, tmp_path / "lost.h5", losses=[lost])
    plain = runner.invoke(app, ["inspect", str(bad)])
    assert plain.exit_code == 0, plain.output  # readable and valid: only --strict refuses it
    assert plain.stdout.splitlines()[0] == "verdict: degraded — ev0: 500 events lost"
    strict = runner.invoke(app, ["inspect", str(bad), "--strict"])
    assert strict.exit_code == STRICT_EXIT, strict.output
    assert "is not complete: degraded — ev0: 500 events lost" in strict.stderr
    as_json = json.loads(runner.invoke(app, ["inspect", str(bad), "--json"]).stdout)
    assert as_json["status"] == "complete"
    assert as_json["verdict"] == "degraded"
    assert as_json["verdict_reasons"] == ["ev0: 500 events lost"]


def test_an_old_take_gets_a_verdict_from_its_stored_records(clean_take: Path, tmp_path: Path) -> None:
    """Nothing new is stored: a take written before the verdict existed gets one too."""
    with h5py.File(clean_take, "r") as f:
        assert not any("verdict" in k for k in f.attrs)
    missed = _with_report(clean_take, tmp_path / "missed.h5", pulses_missing_from_box_log=[4])
    s = summarize(missed)
    assert (s.verdict, s.verdict_reasons) == ("degraded", ["trigger: 1 pulse missing from the box's log"])


def test_the_console_take_list_carries_the_verdict(clean_take: Path, tmp_path: Path) -> None:
    lost = LossRecord(device="cam0", what="frames", count=2, reason="queue full").model_dump()
    _with_report(clean_take, tmp_path / "a.h5", losses=[lost])
    shutil.copy(clean_take, tmp_path / "b.h5")
    entries = {e.name: e for e in TakeList(tmp_path).entries()}
    assert (entries["a.h5"].verdict, entries["a.h5"].verdict_reasons) == ("degraded", ["cam0: 2 frames lost"])
    assert (entries["b.h5"].verdict, entries["b.h5"].verdict_reasons) == ("complete", [])


def test_the_daemon_status_lines_carry_the_verdict() -> None:
    last = {
        "path": "/takes/a.h5",
        "status": "complete",
        "verdict": "degraded",
        "verdict_reasons": ["ev0: 3 of 90 pulses missing"],
        "frames": {"cam0": 90},
        "events": {"ev0": 10},
        "bytes_written": 1_000_000,
        "losses": [],
    }
    assert verdict_text(last) == "degraded — ev0: 3 of 90 pulses missing"
    assert take_summary_line(last).startswith("degraded, 90 frames")
    old_daemon = {k: v for k, v in last.items() if not k.startswith("verdict")}
    assert verdict_text(old_daemon).startswith("unknown")


@pytest.mark.slow
def test_a_daemon_take_reports_its_verdict_and_capture_strict_follows_it(
    start_daemon: Callable[..., RunningDaemon],
) -> None:
    rd = start_daemon()
    endpoint = rd.config.service.control_endpoint
    res = CliRunner().invoke(app, ["capture", "--connect", endpoint, "--duration", "0.5", "--strict"])
    last = rd.client.call("status")["last_take"]
    assert last["status"] == "complete", last
    assert last["verdict"] in ("complete", "degraded"), last
    assert (last["verdict"] == "degraded") == bool(last["verdict_reasons"]), last
    if last["verdict"] == "complete":
        assert res.exit_code == 0, res.output
    else:  # a loaded host can make a sim sensor fall behind: the take then says so
        assert res.exit_code == STRICT_EXIT, res.output
        assert "is not complete: degraded" in res.stderr
    assert f"take: {last['path']} ({last['verdict']}" in res.stdout
    shown = CliRunner().invoke(app, ["status", "--connect", endpoint])
    assert f"verdict: {last['verdict']}" in shown.stdout, shown.output
