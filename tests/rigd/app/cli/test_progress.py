"""Progress as a user meets it: every stage of a long command named, counted in its own unit, with
the time it has left."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
from rich.console import Console
from typer.testing import CliRunner

from firmware_sim.testing.takes import make_take
from rigd.app.cli import app
from rigd.app.commands.progress import StageProgress
from rigd.core.progress import ProgressUpdate


@pytest.mark.slow
def test_capture_names_every_phase_after_the_pulses(small_rig: Path, tmp_path: Path) -> None:
    r = CliRunner().invoke(
        app,
        ["-v", "capture", "--local", "--config", str(small_rig), "--duration", "1", "--out", str(tmp_path)],
    )
    assert r.exit_code == 0, r.output
    lines = [line for line in r.stderr.splitlines() if line.startswith("capture: ")]
    assert [line.split(" (")[0].split(":")[1].strip() for line in lines] == [
        "capturing",
        "waiting for devices",
        "draining",
        "finalizing",
    ]
    assert "(30 pulses)" in lines[0]
    assert "queued items" in lines[2]
    assert "sealing the take" in lines[3]


@pytest.mark.slow
def test_off_a_terminal_stage_lines_need_verbose_and_json_has_none(small_rig: Path, tmp_path: Path) -> None:
    args = ["capture", "--local", "--config", str(small_rig), "-d", "0.5", "--out", str(tmp_path)]
    r = CliRunner().invoke(app, args)  # a script reading the output gets the summary alone
    assert r.exit_code == 0, r.output
    assert "capture: " not in r.stderr
    r = CliRunner().invoke(app, ["-v", *args, "--json"])
    assert r.exit_code == 0, r.output
    assert "capture: " not in r.stderr


def _terminal() -> tuple[Console, io.StringIO]:
    buf = io.StringIO()
    return Console(file=buf, force_terminal=True, width=160, color_system=None), buf


def test_the_bar_counts_each_stage_in_its_unit_with_time_left() -> None:
    console, buf = _terminal()
    with StageProgress(console, "capture") as bar:
        bar.stage("capturing", 30, "pulses")
        bar.advance_to(30)
        bar.stage("draining", 400, "queued items", "the writer writing what is still queued")
        bar.advance_to(100)
    text = buf.getvalue()
    assert "capture: draining" in text
    assert "100/400" in text
    assert "queued items" in text
    assert "left" in text  # "about N s left" or "estimating time left", never a blank


def test_an_uncounted_stage_shows_the_time_so_far() -> None:
    console, buf = _terminal()
    with StageProgress(console, "capture") as bar:
        bar.stage("finalizing", None, "", "fitting the device clocks and sealing the take")
    assert "so far" in buf.getvalue()


def test_workflow_updates_start_a_stage_per_message() -> None:
    plain = Console(file=io.StringIO(), width=160)
    with StageProgress(plain, "calibrate", lines=True) as bar:
        bar(ProgressUpdate("reconstruct", "hpf", 0, 10, "frames"))
        bar(ProgressUpdate("reconstruct", "hpf", 5, 10, "frames"))
        bar(ProgressUpdate("detect", "hpf", 0, 10, "frames searched"))
    lines = plain.file.getvalue().splitlines()  # type: ignore[attr-defined]
    assert lines == ["calibrate: reconstruct (10 frames): hpf", "calibrate: detect (10 frames searched): hpf"]


def test_convert_counts_events_against_the_take_total(tmp_path: Path) -> None:
    take = make_take(tmp_path / "take.h5").path
    r = CliRunner().invoke(app, ["-v", "convert", str(take), str(tmp_path / "ev.raw")])
    assert r.exit_code == 0, r.output
    assert "convert: converting (20,000 events): take.h5 -> ev.raw" in r.stderr
    r = CliRunner().invoke(app, ["-v", "convert", str(tmp_path / "ev.raw"), str(tmp_path / "back.h5")])
    assert r.exit_code == 0, r.output
    assert "convert: converting: ev.raw -> back.h5" in r.stderr  # a recording is counted by decoding it


def test_a_phase_first_seen_after_it_ended_still_shows_its_count() -> None:
    # the CLI polls the capture's progress now and then; a short drain can be over (the take
    # already finalizing) when it first hears of it: the line still says what the drain counted
    from rigd.app.capture.results import Progress
    from rigd.app.commands.capture import _capture_progress

    buf = io.StringIO()
    console = Console(file=buf, force_terminal=False, width=160, color_system=None)
    with StageProgress(console, "capture", lines=True) as bar:
        on_progress = _capture_progress(bar)
        on_progress(Progress(30, 30, {}, {}, 0, "capturing", 30, 30))
        phases = ("capturing", "waiting for devices", "draining", "finalizing")
        entered = {"waiting for devices": 4, "draining": 17}
        on_progress(Progress(30, 30, {}, {}, 0, "finalizing", None, None, phases, entered))
    lines = [line for line in buf.getvalue().splitlines() if line.startswith("capture: ")]
    assert lines[1].startswith("capture: waiting for devices (4 devices)"), lines
    assert lines[2].startswith("capture: draining (17 queued items)"), lines
    assert lines[3].startswith("capture: finalizing: fitting the device clocks"), lines
