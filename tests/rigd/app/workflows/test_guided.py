"""The guided calibration workflow on the built-in sim rig, without the terminal UI."""

from __future__ import annotations

from pathlib import Path

import pytest

from calibration.errors import CalibrationError
from calibration.io import read_opencv_yaml
from rigd.app.workflows.guided import (
    MIN_VIEWS_TO_WRITE,
    GuidedFrame,
    GuidedOptions,
    GuidedProgress,
    GuidedStarted,
    run_guided,
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
