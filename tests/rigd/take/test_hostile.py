"""Hostile take files (issue: a take pointing outside itself, declaring more than it stores, or
carrying malformed metadata): every reader refuses them with one TakeFormatError naming the file
and object, `rigd inspect` and `rigd takes` show the verdict `damaged` first, and nothing the
take points at is ever read."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from firmware_sim.testing.takes import make_take
from rigd.app.cli import app
from rigd.app.take_list import list_takes
from rigd.core.errors import TakeFormatError
from rigd.products.inspect import summarize
from rigd.take import Take
from rigd.take.validate import validate_take

SECRET = b"operator's ssh key: do not copy\n" * 64


@pytest.fixture(scope="module")
def good(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_take(tmp_path_factory.mktemp("hostile") / "good.h5").path


def _copy(good: Path, tmp_path: Path, name: str = "bad.h5") -> Path:
    p = tmp_path / name
    shutil.copy(good, p)
    return p


def _secret(tmp_path: Path) -> Path:
    s = tmp_path / "secret.bin"
    s.write_bytes(SECRET)
    return s


def read_everything(p: Path) -> None:
    """Every read a consumer of a take makes (inspect, export, replay, the console)."""
    with Take(p) as take:
        take.summary()
        _ = take.calibration, take.config, take.journal, take.sync_report, take.pulses
        for c in take.cameras:
            fr = take.camera(c)
            _ = fr.timestamps_us
            if len(fr):
                fr.raw(0)
                fr.rgb(len(fr) - 1)
        for s in take.event_sensors:
            ev = take.sensor(s)
            n = ev.count
            _ = ev.span
            ev.by_index(0, min(n, 100))
            _ = ev.triggers
            if take.time_domain == "rig":
                ev.histogram()
                ev.events()


# -- item 1: a take pointing HDF5 at another file ----------------------------------------------


def _external_storage(p: Path, tmp_path: Path) -> str:
    secret = _secret(tmp_path)
    with h5py.File(p, "r+") as f:
        del f["frames/cam0/images"]
        f.create_dataset("frames/cam0/images", (2, 12, 16, 3), np.uint8, external=[(str(secret), 0, 1152)])
        for k in ("exposure_us", "frame_counter", "host_time_ns", "pulse_index"):
            f[f"frames/cam0/{k}"].resize((2,))
        for k in ("t_exposure_start_device_us", "t_exposure_start_us"):
            f[f"frames/cam0/{k}"].resize((2,))
    return "/frames/cam0/images"


def _external_link(p: Path, tmp_path: Path) -> str:
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as o:
        o["t"] = np.frombuffer(SECRET[:160], np.int64)
    with h5py.File(p, "r+") as f:
        n = f["trigger/pulses/t_us"].shape[0]
        del f["trigger/pulses/t_us"]
        f["trigger/pulses/t_us"] = h5py.ExternalLink(str(other), "/t")
        assert n == 10
    return "/trigger/pulses/t_us"


def _virtual(p: Path, tmp_path: Path) -> str:
    other = tmp_path / "src.h5"
    with h5py.File(other, "w") as o:
        o["x"] = np.frombuffer(SECRET[:40000], np.uint16)[:20000]
    layout = h5py.VirtualLayout(shape=(20000,), dtype=np.uint16)
    layout[:] = h5py.VirtualSource(str(other), "x", shape=(20000,))
    with h5py.File(p, "r+") as f:
        del f["events/ev0/x"]
        f.create_virtual_dataset("events/ev0/x", layout)
    return "/events/ev0/x"


@pytest.mark.parametrize("make", [_external_storage, _external_link, _virtual])
def test_take_pointing_at_another_file_is_refused_unread(
    good: Path, tmp_path: Path, make: Callable[[Path, Path], str]
) -> None:
    p = _copy(good, tmp_path)
    hpath = make(p, tmp_path)
    with pytest.raises(TakeFormatError, match=rf"{p}: {hpath}: .*(external|virtual)"):
        Take(p)
    problems = validate_take(p)
    assert len(problems) == 1
    assert hpath in problems[0]
    with pytest.raises(TakeFormatError, match=hpath):
        summarize(p)
    r = CliRunner().invoke(app, ["inspect", str(p)])
    assert r.exit_code == 2, r.output
    assert r.stdout.startswith("verdict: damaged"), r.output
    assert r.stderr.startswith(f"error: {p}: {hpath}"), r.stderr
    assert "Traceback" not in r.output
    assert "ssh key" not in r.output


def test_export_of_a_take_with_external_storage_writes_nothing(good: Path, tmp_path: Path) -> None:
    p = _copy(good, tmp_path)
    _external_storage(p, tmp_path)
    out = tmp_path / "out"
    r = CliRunner().invoke(app, ["export", str(p), "--format", "colmap", "--out", str(out)])
    assert r.exit_code != 0
    assert "/frames/cam0/images" in r.output
    assert "external" in r.output
    assert "Traceback" not in r.output
    assert not any(b"ssh key" in f.read_bytes() for f in out.rglob("*") if f.is_file())


def test_a_fifo_named_like_a_take_is_not_opened(tmp_path: Path) -> None:
    fifo = tmp_path / "pipe.h5"
    import os

    os.mkfifo(fifo)
    with pytest.raises(TakeFormatError, match="not a regular file"):
        Take(fifo)  # opening a FIFO for reading would block until a writer comes


# -- item 4: declared sizes the file does not hold ---------------------------------------------


def _huge_events(f: h5py.File) -> str:
    for k in ("t", "x", "y", "p"):
        f[f"events/ev0/{k}"].resize((600_000_000,))
    return "/events/ev0/"


def _huge_trigger(f: h5py.File) -> str:
    for k in ("t", "t_device", "host_time_ns", "p", "channel"):
        f[f"events/ev0/trigger/{k}"].resize((300_000_000,))
    return "/events/ev0/trigger/"


def _contiguous_unwritten(f: h5py.File) -> str:
    del f["events/ev0/ms_to_idx"]
    f.create_dataset("events/ev0/ms_to_idx", (400_000_000,), np.uint64)  # never written
    return "/events/ev0/ms_to_idx"


def _compressed_index(f: h5py.File) -> str:
    # Written, not a gap: 400 MB of zeros that deflate to well under 1/1000 of that.
    g = f["trigger/pulses"]
    del g["index"]
    ds = g.create_dataset("index", (50_000_000,), np.int64, chunks=(1 << 20,), compression="gzip")
    block = np.zeros(1 << 20, np.int64)
    for start in range(0, ds.shape[0], block.size):
        n = min(block.size, ds.shape[0] - start)
        ds[start : start + n] = block[:n]
    return "/trigger/pulses/index"


@pytest.mark.parametrize("edit", [_huge_events, _huge_trigger, _contiguous_unwritten, _compressed_index])
def test_declared_size_beyond_the_stored_bytes_is_refused_before_any_read(
    good: Path, tmp_path: Path, edit: Callable[[h5py.File], str]
) -> None:
    p = _copy(good, tmp_path)
    with h5py.File(p, "r+") as f:
        hpath = edit(f)
    assert p.stat().st_size < 2_000_000
    with pytest.raises(TakeFormatError, match=rf"{hpath}.*declares [\d,]+ bytes"):
        read_everything(p)


# -- item 5: one malformed take does not spoil the list -------------------------------------------


def test_one_malformed_take_is_one_damaged_row_of_the_list(good: Path, tmp_path: Path) -> None:
    d = tmp_path / "takes"
    d.mkdir()
    shutil.copy(good, d / "a.h5")
    bad = _copy(good, d, "b.h5")
    with h5py.File(bad, "r+") as f:
        f["events/ev0"].attrs["width"] = "wide"
    rows = {r.name: r for r in list_takes(d)}
    assert rows["a"].verdict == "complete"
    assert rows["b"].verdict == "damaged"
    assert rows["b"].error is not None
    assert str(bad) in rows["b"].error
    r = CliRunner().invoke(app, ["takes", str(d)])
    assert r.exit_code == 0, r.output
    assert "damaged" in r.output
    assert "Traceback" not in r.output


# -- item 6: link loops, damaged indexes, phantom frames -----------------------------------------


def test_soft_link_loop_is_refused_in_one_line(good: Path, tmp_path: Path) -> None:
    p = _copy(good, tmp_path)
    with h5py.File(p, "r+") as f:
        f.create_group("calibration")
        f["calibration/a"] = h5py.SoftLink("/calibration/b")
        f["calibration/b"] = h5py.SoftLink("/calibration/a")
    with pytest.raises(TakeFormatError, match="/calibration/a: is a soft link"):
        Take(p)
    for args in (["inspect", str(p)], ["export", str(p), "--format", "colmap", "--out", str(tmp_path / "o")]):
        r = CliRunner().invoke(app, args)
        assert r.exit_code != 0, r.output
        assert "Traceback" not in r.output
        assert "soft link" in r.output


def test_damaged_index_shows_damaged_first(good: Path, tmp_path: Path) -> None:
    p = _copy(good, tmp_path)
    with h5py.File(p, "r+") as f:
        f["events/ev0/ms_to_idx"][5] = 19_999
    r = CliRunner().invoke(app, ["inspect", str(p)])
    assert r.exit_code == 1
    assert r.output.startswith("verdict: damaged"), r.output
    assert "nothing lost" not in r.output
    assert summarize(p).verdict == "damaged"


def test_phantom_frames_are_refused(good: Path, tmp_path: Path) -> None:
    p = _copy(good, tmp_path)
    with h5py.File(p, "r+") as f:
        g = f["frames/cam0"]
        for k in g:
            g[k].resize((20_000_000, *g[k].shape[1:]))
    with pytest.raises(TakeFormatError, match=r"/frames/cam0/.*declares"):
        read_everything(p)
    assert CliRunner().invoke(app, ["inspect", str(p)]).stdout.startswith("verdict: damaged")


# -- item 7: malformed metadata is one TakeFormatError -------------------------------------------


def _attr(hpath: str, key: str, value: object) -> Callable[[h5py.File], None]:
    def edit(f: h5py.File) -> None:
        f[hpath].attrs[key] = value

    edit.__name__ = f"{hpath}@{key}={value!r}"[:60]
    return edit


def _float_images(f: h5py.File) -> None:
    data = f["frames/cam0/images"][...].astype(np.float32)
    del f["frames/cam0/images"]
    f.create_dataset("frames/cam0/images", data=data, chunks=(1, 12, 16, 3), maxshape=(None, 12, 16, 3))


def _deep_calibration(f: h5py.File) -> None:
    g = f.create_group("calibration/cam0")
    g["K"] = np.eye(3)
    g["result_json"] = "[" * 100_000 + "]" * 100_000


def _string_t_offset(f: h5py.File) -> None:
    del f["events/ev0/t_offset"]
    f["events/ev0/t_offset"] = "soon"


def _report_garbage(f: h5py.File) -> None:
    del f["sync/report_json"]
    f["sync/report_json"] = json.dumps({"n_pulses": "many"})


def _two_d_pulses(f: h5py.File) -> None:
    del f["trigger/pulses/t_us"]
    f["trigger/pulses/t_us"] = np.zeros((10, 3), np.int64)


def _compound(f: h5py.File) -> None:
    del f["frames/cam0/exposure_us"]
    f["frames/cam0/exposure_us"] = np.zeros(9, dtype=[("a", "<i8"), ("b", "<f4")])


def _short_column(f: h5py.File) -> None:  # found by test_take_fuzz
    f["events/ev0/p"].resize((0,))


METADATA_EDITS = [
    _short_column,
    _attr("events/ev0", "width", "wide"),
    _attr("events/ev0", "height", 2**62),
    _attr("frames/cam0", "width", -3),
    _attr("frames/cam0", "pixel_format", "rgb99"),
    _attr("/", "schema_version", 7),
    _float_images,
    _deep_calibration,
    _string_t_offset,
    _report_garbage,
    _two_d_pulses,
    _compound,
]


@pytest.mark.parametrize("edit", METADATA_EDITS, ids=lambda e: e.__name__)
def test_malformed_metadata_is_one_take_format_error(
    good: Path, tmp_path: Path, edit: Callable[[h5py.File], None]
) -> None:
    p = _copy(good, tmp_path)
    with h5py.File(p, "r+") as f:
        edit(f)
    with pytest.raises(TakeFormatError, match=str(p)):
        read_everything(p)
    r = CliRunner().invoke(app, ["inspect", str(p)])
    assert "Traceback" not in r.output
    assert r.exit_code in (1, 2), r.output


def test_replay_of_a_take_pointing_outside_is_refused(good: Path, tmp_path: Path) -> None:
    p = _copy(good, tmp_path)
    _external_storage(p, tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    r = CliRunner().invoke(app, ["capture", "--replay", str(p), "--out", str(out)])
    assert r.exit_code == 2, r.output
    assert "/frames/cam0/images" in r.output
    assert "external" in r.output
    assert "Traceback" not in r.output
    assert not list(out.iterdir())
