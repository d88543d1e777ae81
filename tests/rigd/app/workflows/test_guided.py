"""The guided calibration workflow on the built-in sim rig, without the terminal UI."""

from __future__ import annotations

from pathlib import Path
from unittest.mock import MagicMock

import pytest

from calibration.errors import CalibrationError
from calibration.intrinsics import RECOMMENDED_VIEWS, IntrinsicsResult
from calibration.io import read_opencv_yaml
from rigd.app.workflows.guided import (
    MIN_VIEWS_TO_WRITE,
    GuidedFrame,
    GuidedOptions,
    GuidedOutcome,
    GuidedProgress,
    GuidedStarted,
    SessionBudget,
    run_guided,
    verdict,
    views_text,
)
from rigd.core.errors import RigdError


@pytest.mark.slow
def test_guided_session_reports_every_frame_and_writes_the_result(tmp_path: Path) -> None:
    out = tmp_path / "cam0.yaml"
    updates: list[GuidedProgress] = []
    options = GuidedOptions(
        camera="cam0", out=out, resolution=(320, 180), max_seconds=6.0, still_px=2.0, min_views=3
    )
    outcome = run_guided(options, updates.append)
    started, frames = updates[0], updates[1:]
    assert isinstance(started, GuidedStarted)
    assert started.frame_size == (320, 180)
    assert "scene=board" in started.spec
    assert all(isinstance(u, GuidedFrame) for u in frames)
    assert len(frames) == outcome.frames > 0
    if outcome.n_views >= MIN_VIEWS_TO_WRITE:
        assert outcome.result is not None
        _, _, size = read_opencv_yaml(out)
        assert size == (320, 180)
    else:
        assert outcome.result is None
        assert not out.exists()


def test_unknown_camera_is_a_rigd_error(tmp_path: Path) -> None:
    options = GuidedOptions(camera="nope", out=tmp_path / "x.yaml", max_seconds=1.0)
    with pytest.raises(RigdError, match="no RGB camera 'nope'"):
        run_guided(options)


def test_bad_session_settings_close_the_devices_and_raise(tmp_path: Path) -> None:
    """The session is made after the devices open: its error still closes them, so a second run
    can open the same sim devices again."""
    options = GuidedOptions(camera="cam0", out=tmp_path / "x.yaml", resolution=(160, 90), model="nope")
    for _ in range(2):
        with pytest.raises(CalibrationError, match="unknown lens model"):
            run_guided(options)


def _outcome(n_views: int, sigmas: dict[str, float], used: int | None = None) -> GuidedOutcome:
    result = MagicMock(spec=IntrinsicsResult)
    result.std_devs = sigmas
    result.views = [object()] * (n_views if used is None else used)
    return GuidedOutcome(
        camera="cam0", done=False, n_views=n_views, frames=100, skipped=0, result=None
    ).model_copy(update={"result": result})


def test_verdict_is_judged_on_the_written_result() -> None:
    """The verdict reads the written result, by the session's stop rule: its std devs against the
    target, and the views it used (outliers it rejected do not count) against `done_views`."""
    low = {"fx": 0.3, "fy": 0.3, "cx": 0.2, "cy": 0.25}
    reached, text = verdict(_outcome(10, low), 0.5, 10)
    assert reached
    assert text == "target reached"
    reached, text = verdict(_outcome(6, low), 0.5, 10)
    assert not reached
    assert "6 usable views of the 10 needed" in text
    assert "below the 0.5 px target" in text
    # 11 kept, 2 rejected by the fit: 9 used, not enough
    reached, text = verdict(_outcome(11, low, used=9), 0.5, 10)
    assert not reached
    assert "9 usable views" in text
    reached, text = verdict(_outcome(12, {**low, "fx": 0.7}), 0.5, 10)
    assert not reached
    assert "fx 0.700" in text
    assert "fy" not in text
    none = GuidedOutcome(camera="cam0", done=False, n_views=2, frames=10, skipped=0, result=None)
    assert verdict(none, 0.5, 10) == (False, "only 2 view(s) captured; nothing written")


def test_views_are_counted_one_way() -> None:
    low = {"fx": 0.3, "fy": 0.3, "cx": 0.2, "cy": 0.25}
    assert views_text(_outcome(24, low, used=23)) == "23 views (24 kept, 1 rejected as outliers)"
    assert views_text(_outcome(12, low)) == "12 views"


def test_done_views_is_the_reports_recommendation() -> None:
    assert GuidedOptions(camera="cam0").done_views == RECOMMENDED_VIEWS
    assert GuidedOptions(camera="cam0", min_views=15).done_views == 15


@pytest.mark.slow
def test_cli_on_the_sim_board_reaches_the_target_the_same_way_on_any_machine(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`rigd calibrate guided --camera cam0 --sim-clock virtual` (the README's command on virtual
    time): writes takes/calibration/cam0-<UTC time>.yaml (a new file each run, nothing in the
    working directory itself) and reaches the target on the sim board (its
    default still_px judges the smear). On virtual time every frame is looked at and the limit is
    the camera's time, so two runs agree to the digit however loaded the host is; in real time
    (the default) the host's load decides which frames the session sees."""
    from typer.testing import CliRunner

    from rigd.app.cli import app

    monkeypatch.chdir(tmp_path)
    lasts = []
    seen: set[Path] = set()
    for _ in range(2):
        r = CliRunner().invoke(
            app, ["calibrate", "guided", "--camera", "cam0", "--max-seconds", "90", "--sim-clock", "virtual"]
        )
        assert r.exit_code == 0, r.output
        assert "target reached" in r.output
        assert "time ran out" not in r.output
        # off a terminal: no line per frame, a line per capture and a status line every few seconds
        assert len(r.output.splitlines()) < 80, r.output
        assert "-0 s" not in r.output
        now = set((tmp_path / "takes" / "calibration").glob("cam0-*.yaml"))
        (new,) = now - seen  # each run its own file, named in the verdict line
        seen = now
        assert f"-> {new.relative_to(tmp_path)}" in r.stderr, r.stderr
        _, _, size = read_opencv_yaml(new)
        assert size == (640, 360)
        assert [p.name for p in tmp_path.iterdir()] == ["takes"]
        lasts.append(r.stderr.strip().splitlines()[-1].rsplit(" -> ", 1)[0])  # each its own file
    assert lasts[0] == lasts[1], lasts


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--sim-clock", "fast"], "--sim-clock 'fast': use real or virtual"),
        (
            ["--sim-clock", "virtual", "--config", "rig.json"],
            "in a config, give every sim:// spec clock=virtual",
        ),
    ],
)
def test_a_sim_clock_the_session_cannot_use_is_refused_in_one_line(args: list[str], says: str) -> None:
    from typer.testing import CliRunner

    from rigd.app.cli import app

    r = CliRunner().invoke(app, ["calibrate", "guided", "--camera", "cam0", *args])
    assert r.exit_code == 2, r.output
    assert says in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr


class _Wall:
    """A wall clock the test moves."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_budget_in_real_time_counts_wall_seconds() -> None:
    wall = _Wall()
    budget = SessionBudget(10.0, device_time=False, wall=wall)
    budget.saw(5_000_000_000)  # frame times do not matter in real time
    wall.now += 4.0
    assert budget.left() == pytest.approx(6.0)
    assert not budget.spent
    wall.now += 6.0
    assert budget.left() == 0.0
    assert budget.spent


def test_budget_on_virtual_time_counts_the_cameras_time_not_the_hosts() -> None:
    wall = _Wall()
    budget = SessionBudget(10.0, device_time=True, wall=wall)
    assert budget.left() == 10.0
    budget.saw(2_000_000)
    wall.now += 25.0  # a loaded host: long between frames, the camera's time has not moved
    budget.saw(2_033_333)
    assert budget.left() == pytest.approx(10.0 - 0.033333)
    assert not budget.spent
    budget.saw(12_000_000)
    assert budget.left() == 0.0
    assert budget.spent


def test_budget_on_virtual_time_ends_when_the_sim_stops_sending_frames() -> None:
    wall = _Wall()
    budget = SessionBudget(10.0, device_time=True, wall=wall)
    budget.saw(1_000_000)
    wall.now += SessionBudget.STALL_S - 0.1
    assert not budget.spent
    wall.now += 0.1
    assert budget.stalled
    assert budget.spent
    assert budget.left() == 10.0  # the camera's time left is still shown as it is


@pytest.mark.slow
def test_event_sensor_session_on_reconstructed_frames(tmp_path: Path) -> None:
    """An event sensor goes through the same session on images reconstructed from its events
    (e2calib's hpf): the sim board is found in them, views are kept and a calibration written."""
    out = tmp_path / "ev0.yaml"
    options = GuidedOptions(
        camera="ev0", out=out, resolution=(320, 180), max_seconds=20.0, min_views=3, target_sigma_px=50.0
    )
    updates: list[GuidedProgress] = []
    outcome = run_guided(options, updates.append)
    started = updates[0]
    assert isinstance(started, GuidedStarted)
    assert started.frame_size == (320, 180)
    assert "ev0" in started.spec
    assert "scene=board" in started.spec
    assert outcome.n_views >= 3, [u.feedback.reason for u in updates[1:] if isinstance(u, GuidedFrame)][-20:]
    assert outcome.result is not None
    _, _, size = read_opencv_yaml(out)
    assert size == (320, 180)
