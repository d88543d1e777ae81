"""`rigd capture --scene board`: every sim camera and event sensor films the calibration board, so
a sim rig records a take to calibrate from (docs/calibration.md, *Recording a calibration take*)."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from rigd.app.cli import app
from rigd.app.config import RigConfig, default_sim_rig, with_sim_scene
from rigd.core.errors import ConfigError

runner = CliRunner()


def test_the_scene_goes_on_every_sim_camera_and_sensor_not_the_trigger() -> None:
    rig = with_sim_scene(default_sim_rig(), "board")
    for dev in [*rig.cameras, *rig.event_sensors]:
        assert dev.spec.endswith("&scene=board"), dev.spec
    assert "scene" not in rig.trigger.spec
    again = with_sim_scene(rig, "sprites")  # replaces, never repeats, the parameter
    assert all(d.spec.count("scene=") == 1 and d.spec.endswith("scene=sprites") for d in again.cameras)
    with pytest.raises(ConfigError, match="use sprites or board"):
        with_sim_scene(rig, "forest")
    data = default_sim_rig().model_dump(mode="json")
    for dev in [*data["cameras"], *data["event_sensors"]]:
        dev["spec"] = "file:///tmp/clip.mp4"
    with pytest.raises(ConfigError, match="applies to sim:// cameras and event sensors"):
        with_sim_scene(RigConfig.from_data(data), "board")


def test_replay_and_scene_refused_together(tmp_path: Path) -> None:
    r = runner.invoke(app, ["capture", "--replay", str(tmp_path / "t.h5"), "--scene", "board"])
    assert r.exit_code == 2
    assert "drop --scene" in r.output


@pytest.mark.slow
def test_a_board_take_shows_the_board_to_every_camera(small_rig: Path, tmp_path: Path) -> None:
    from calibration.boards import detect, parse_board
    from rigd.take.reader import Take

    out = tmp_path / "takes"
    r = runner.invoke(
        app, ["capture", "--config", str(small_rig), "--scene", "board", "--duration", "1", "--out", str(out)]
    )
    assert r.exit_code == 0, r.output
    (take_path,) = out.glob("*.h5")
    board = parse_board("chessboard:9x6:0.08")
    with Take(take_path) as take:
        for cam in take.cameras:
            frames = take.camera(cam)
            seen = sum(
                detect(frames[i].image, board, f"{cam}-{i}") is not None for i in range(0, len(frames), 5)
            )
            assert seen >= 1, f"{cam}: the board in none of its frames"
        assert all(d["spec"].endswith("scene=board") for d in take.config["cameras"])
