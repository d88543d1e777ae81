"""`simulate-events` as the lead registers it: typer.Typer().command("simulate-events")."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from firmware_sim.cli import parse_noise, simulate_events
from firmware_sim.testing.frames import make_folder
from rigd.take import open_take, validate_take

app = typer.Typer()
app.command("simulate-events")(simulate_events)


@app.callback()
def _root() -> None:
    """Keeps simulate-events a named sub-command, as in rigd/app/cli.py."""


@pytest.mark.slow
def test_simulate_folder_to_take(tmp_path: Path) -> None:
    folder = make_folder(tmp_path)
    out = tmp_path / "ev.h5"
    res = CliRunner().invoke(
        app,
        [
            "simulate-events",
            str(folder),
            "--out",
            str(out),
            "--fps",
            "30",
            "--threshold",
            "0.2",
            "--sigma",
            "0.02",
            "--seed",
            "4",
            "--noise",
            "leak=0.5,shot",
            "--width",
            "30",
            "--with-frames",
        ],
    )
    assert res.exit_code == 0, res.output
    assert "5 frames" in res.output
    with open_take(out) as take:
        assert take.sensor("ev0").geometry == (30, 20)
        assert take.sensor("ev0").count > 0
        assert len(take.camera("cam0")) == 5
        model = take.config["simulator"]["pixel_model"]
        assert (model["threshold"], model["sigma"], model["seed"]) == (0.2, 0.02, 4)
        assert model["leak_rate_hz"] == 0.5
        assert model["shot_noise_rate_hz"] == 0.1
    assert validate_take(out) == []


@pytest.mark.slow
def test_fixed_substeps(tmp_path: Path) -> None:
    folder = make_folder(tmp_path)
    out = tmp_path / "ev.h5"
    args = ["simulate-events", str(folder), "--out", str(out), "--fps", "10", "--substeps", "4"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "max 4" in res.output


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--noise", "sparkle"], "unknown noise term 'sparkle'"),
        (["--substeps", "2", "--max-px-per-step", "1"], "not both"),
        (["--threshold", "-1"], "threshold"),
    ],
)
def test_bad_options_are_clear_errors(tmp_path: Path, extra: list[str], message: str) -> None:
    folder = make_folder(tmp_path, 2)
    res = CliRunner().invoke(app, ["simulate-events", str(folder), "--out", str(tmp_path / "x.h5"), *extra])
    assert res.exit_code == 2
    assert message in " ".join(res.output.split())


def test_missing_fps_and_missing_input(tmp_path: Path) -> None:
    folder = make_folder(tmp_path, 2)
    res = CliRunner().invoke(app, ["simulate-events", str(folder), "--out", str(tmp_path / "x.h5")])
    assert res.exit_code == 2
    assert "pass --fps" in " ".join(res.output.split())
    res = CliRunner().invoke(
        app, ["simulate-events", str(tmp_path / "nope"), "--out", str(tmp_path / "y.h5")]
    )
    assert res.exit_code == 2
    assert "no such file" in " ".join(res.output.split())


def test_parse_noise() -> None:
    assert parse_noise("hot=0.001, refractory=250,lowpass") == {
        "hot_pixel_fraction": 0.001,
        "refractory_us": 250,
        "lowpass": True,
        "lowpass_cutoff_hz": 300.0,
    }
    assert parse_noise(None) == {}


@pytest.mark.slow
def test_rigd_cli_has_simulate_events_through_the_plugin_entry_point(tmp_path: Path) -> None:
    from rigd.app.cli import app as rigd_app

    folder = make_folder(tmp_path)
    out = tmp_path / "ev.h5"
    res = CliRunner().invoke(rigd_app, ["simulate-events", str(folder), "--out", str(out), "--fps", "30"])
    assert res.exit_code == 0, res.output
    with open_take(out) as take:
        assert take.event_sensors == ["ev0"]
        assert len(take.sensor("ev0").events()) > 0


@pytest.mark.slow
def test_simulate_to_evt3_raw_decodes_to_the_take_events(tmp_path: Path) -> None:
    from rigd.evt import read_raw

    folder = make_folder(tmp_path)
    args = ["simulate-events", str(folder), "--fps", "30", "--seed", "2", "--out"]
    assert CliRunner().invoke(app, [*args, str(tmp_path / "ev.h5")]).exit_code == 0
    res = CliRunner().invoke(app, [*args, str(tmp_path / "ev.raw")])
    assert res.exit_code == 0, res.output
    hdr, dec = read_raw(tmp_path / "ev.raw", strict=True)
    with open_take(tmp_path / "ev.h5") as take:
        ref = take.sensor("ev0").events()
    assert (hdr.width, hdr.height) == take_geometry(tmp_path / "ev.h5")
    np.testing.assert_array_equal(dec.events.t, ref.t)
    np.testing.assert_array_equal(dec.events.x, ref.x)
    np.testing.assert_array_equal(dec.events.p, ref.p)


def take_geometry(path: Path) -> tuple[int, int]:
    with open_take(path) as take:
        return take.sensor("ev0").geometry
