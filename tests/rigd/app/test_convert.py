"""`rigd convert`: real recordings to takes and back, identical events."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from drivers.evt import read_dat, read_raw
from rigd.app.cli import app
from rigd.app.convert import ConvertError, convert
from rigd.take.reader import Take

DATA = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "events"
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"shared test data not found at {DATA}")


@pytest.mark.parametrize("name", ["evt3_gen41_sample.raw", "evt2_gen3_sample.raw", "evt3_pedestrians.raw"])
@pytest.mark.parametrize("fmt", ["evt3", "evt2", "evt21"])
def test_raw_take_raw_round_trip(tmp_path: Path, name: str, fmt: str) -> None:
    src = DATA / name
    hdr, ref = read_raw(src)
    take_path = tmp_path / "t.h5"
    assert convert(src, take_path) == len(ref.events)
    with Take(take_path) as take:
        ev = take.events("ev0")
        assert take.geometry("ev0") == (hdr.width, hdr.height)
        for col in ("x", "y", "p", "t"):
            np.testing.assert_array_equal(getattr(ev, col), getattr(ref.events, col))
        np.testing.assert_array_equal(take.triggers("ev0").t, ref.triggers.t)
    back = tmp_path / f"back.{fmt}.raw"
    convert(take_path, back, fmt=fmt)
    hdr2, again = read_raw(back)
    assert (hdr2.width, hdr2.height, hdr2.fmt) == (hdr.width, hdr.height, fmt)
    for col in ("x", "y", "p", "t"):
        np.testing.assert_array_equal(getattr(again.events, col), getattr(ref.events, col))


def test_dat_round_trip(tmp_path: Path) -> None:
    src = DATA / "dat_ncars_sample.dat"
    _, ref = read_dat(src)
    convert(src, tmp_path / "d.h5")
    convert(tmp_path / "d.h5", tmp_path / "d.dat")
    _, again = read_dat(tmp_path / "d.dat")
    np.testing.assert_array_equal(again.t, ref.t)
    np.testing.assert_array_equal(again.x, ref.x)


def test_cli_convert_then_inspect_shows_the_same_events(tmp_path: Path) -> None:
    runner = CliRunner()
    take_path = tmp_path / "ped.h5"
    r = runner.invoke(app, ["convert", str(DATA / "evt3_pedestrians.raw"), str(take_path)])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["inspect", str(take_path), "--json"])
    assert r.exit_code == 0, r.output
    summary = json.loads(r.output)
    assert summary["event_sensors"]["ev0"]["events"] == 5_000
    r = runner.invoke(app, ["convert", str(take_path), str(tmp_path / "x.txt")])
    assert r.exit_code == 2
    assert "cannot convert" in r.output


def test_refuses_to_overwrite_and_names_missing_sensor(tmp_path: Path) -> None:
    take_path = tmp_path / "t.h5"
    convert(DATA / "evt3_pedestrians.raw", take_path)
    with pytest.raises(ConvertError, match="exists"):
        convert(DATA / "evt3_pedestrians.raw", take_path)
    with pytest.raises(ConvertError, match="no event sensor 'ev9'"):
        convert(take_path, tmp_path / "o.raw", sensor="ev9")
