"""`rigd convert`: real recordings to takes and back, identical events."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from rigd.app.cli import app
from rigd.evt import RawHeader, parse_raw_header, read_dat, read_raw, write_dat, write_raw
from rigd.products.convert import ConvertError, convert
from rigd.take.reader import Take

DATA = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "events"
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"shared test data not found at {DATA}")


@pytest.mark.slow
@pytest.mark.parametrize("name", ["evt3_gen41_sample.raw", "evt2_gen3_sample.raw", "evt3_pedestrians.raw"])
@pytest.mark.parametrize("fmt", ["evt3", "evt2", "evt21"])
def test_raw_take_raw_round_trip(tmp_path: Path, name: str, fmt: str) -> None:
    src = DATA / name
    hdr, ref = read_raw(src)
    take_path = tmp_path / "t.h5"
    assert convert(src, take_path) == len(ref.events)
    with Take(take_path) as take:
        ev = take.sensor("ev0").events()
        assert take.sensor("ev0").geometry == (hdr.width, hdr.height)
        for col in ("x", "y", "p", "t"):
            np.testing.assert_array_equal(getattr(ev, col), getattr(ref.events, col))
        np.testing.assert_array_equal(take.sensor("ev0").triggers.t, ref.triggers.t)
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


@pytest.mark.slow
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


def _zero_a_time_low(src: Path, dst: Path) -> int:
    """Copy a real EVT3 recording with one TIME_LOW in the middle set to 0; returns its offset."""
    data = bytearray(src.read_bytes())
    with src.open("rb") as f:
        start = parse_raw_header(f).size
    words = np.frombuffer(bytes(data[start:]), "<u2", (len(data) - start) // 2)
    tl = np.flatnonzero((words >> 12) == 6)
    off = start + 2 * int(tl[len(tl) // 2])
    data[off : off + 2] = (0x6000).to_bytes(2, "little")
    dst.write_bytes(bytes(data))
    return off


def test_one_corrupt_word_costs_only_its_events(tmp_path: Path) -> None:
    src = tmp_path / "rec.raw"
    off = _zero_a_time_low(DATA / "evt3_gen41_sample.raw", src)
    _, ref = read_raw(DATA / "evt3_gen41_sample.raw")
    r = CliRunner().invoke(app, ["convert", str(src), str(tmp_path / "t.h5")])
    assert r.exit_code == 0, r.output
    with Take(tmp_path / "t.h5") as take:
        ev = take.sensor("ev0").events()
        report = take.sync_report
    assert report is not None
    (loss,) = report.losses
    assert "non_monotonic_time" in loss.reason
    assert len(ev) + loss.count == len(ref.events)
    assert 0 < loss.count < 1000
    assert str(off) in loss.reason or any(str(o) in loss.reason for o in range(off, off + 4096, 2))
    assert (np.diff(ev.t) >= 0).all()
    with pytest.raises(ConvertError, match="non_monotonic_time at byte offset"):
        convert(src, tmp_path / "strict.h5", strict=True)
    assert not (tmp_path / "strict.h5").exists()


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _dir(tmp_path: Path) -> Path:
    d = tmp_path / "rec.raw"
    d.mkdir()
    return d


@pytest.mark.parametrize(
    ("make", "problem"),
    [
        (
            lambda d: _write(d / "w.raw", b"% format EVT3;width=abc;height=720\n% end\n" + bytes(64)),
            "is not an integer",
        ),
        (lambda d: _write(d / "g.raw", b"% evt 3.0\n% geometry axb\n" + bytes(64)), "is not an integer"),
        (lambda d: _write(d / "big.raw", b"% format EVT3;width=4096;height=720\n% end\n"), "outside 1..2048"),
        (lambda d: _write(d / "z.raw", b""), "empty file"),
        (lambda d: _write(d / "v.raw", b"% format EVT3;width=abc\n"), "format width 'abc' is not an integer"),
        (lambda d: _write(d / "r.raw", np.random.default_rng(1).bytes(4096)), "no RAW header"),
        (lambda d: _write(d / "h.raw", b"% evt 3.0\n% end\n"), "no events decoded: it holds no event data"),
        (lambda d: _write(d / "d.dat", b"% Height x\n\x0c\x08" + bytes(16)), "Height 'x' is not an integer"),
        (lambda d: _write(d / "s.dat", b"% Width 4\n\x0c\x07" + bytes(16)), "DAT event size 7"),
        (lambda d: _write(d / "e.dat", b""), "empty file"),
        (_dir, "is a directory"),
    ],
)
@pytest.mark.slow
def test_unreadable_input_is_one_line_naming_the_file(
    tmp_path: Path, make: Callable[[Path], Path], problem: str
) -> None:
    src = make(tmp_path)
    dst = tmp_path / "out.h5"
    r = CliRunner().invoke(app, ["convert", str(src), str(dst)])
    assert r.exit_code in (1, 2), r.output
    assert problem in r.output
    assert str(src) in r.output
    assert "Traceback" not in r.output
    assert len(r.output.strip().splitlines()) == 1, r.output
    assert not dst.exists()  # nothing half-done left behind


def test_geometry_that_puts_every_event_out_of_range(tmp_path: Path) -> None:
    _, ref = read_raw(DATA / "evt3_pedestrians.raw")
    src = tmp_path / "tiny.raw"
    write_raw(src, RawHeader(fmt="evt3", width=1280, height=720), ref.events)
    data = (
        src.read_bytes().replace(b"height=720;width=1280", b"height=2;width=2").replace(b"1280x720", b"2x2")
    )
    src.write_bytes(data)
    r = CliRunner().invoke(app, ["convert", str(src), str(tmp_path / "o.h5")])
    assert r.exit_code in (1, 2), r.output
    assert "no events decoded" in r.output
    assert "out_of_range_xy" in r.output
    assert str(src) in r.output
    assert not (tmp_path / "o.h5").exists()


def test_existing_take_with_data_is_kept(tmp_path: Path) -> None:
    take_path = tmp_path / "t.h5"
    convert(DATA / "evt3_pedestrians.raw", take_path)
    before = take_path.read_bytes()
    r = CliRunner().invoke(app, ["convert", str(tmp_path / "missing.raw"), str(take_path)])
    assert r.exit_code in (1, 2)
    r = CliRunner().invoke(app, ["convert", str(DATA / "evt3_pedestrians.raw"), str(take_path)])
    assert r.exit_code in (1, 2)
    assert "exists" in r.output
    assert take_path.read_bytes() == before


def test_dat_record_out_of_time_order_is_a_loss(tmp_path: Path) -> None:
    src = tmp_path / "rec.dat"
    _, ref = read_dat(DATA / "dat_ncars_sample.dat")
    write_dat(src, ref, width=int(ref.x.max()) + 1, height=int(ref.y.max()) + 1)
    data = bytearray(src.read_bytes())
    off = len(data) - 8 * len(ref) + 8 * (len(ref) // 2)
    data[off : off + 4] = (0).to_bytes(4, "little")  # one record's time zeroed
    src.write_bytes(bytes(data))
    assert convert(src, tmp_path / "d.h5") == len(ref) - 1
    with Take(tmp_path / "d.h5") as take:
        report = take.sync_report
        assert take.sensor("ev0").count == len(ref) - 1
    assert report is not None
    (loss,) = report.losses
    assert loss.count == 1
    assert f"[{off}]" in loss.reason
