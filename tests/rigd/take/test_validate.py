"""validate_take names the HDF5 path of every problem; broken and unfinished takes still open."""

from __future__ import annotations

import shutil
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest

from firmware_sim.testing.takes import make_take
from rigd.core.errors import TakeError
from rigd.take import open_take, validate_take


@pytest.fixture(scope="module")
def good(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_take(tmp_path_factory.mktemp("v") / "good.h5").path


def _corrupt(good: Path, tmp_path: Path, edit: Callable[[h5py.File], None]) -> list[str]:
    p = tmp_path / "bad.h5"
    shutil.copy(good, p)
    with h5py.File(p, "r+") as f:
        edit(f)
    return validate_take(p)


def _replace(f: h5py.File, path: str, data: np.ndarray) -> None:
    del f[path]
    f.create_dataset(path, data=data)


def _one(problems: list[str], *needles: str) -> None:
    assert any(all(n in p for n in needles) for p in problems), problems


def test_good_take_has_no_problems(good: Path) -> None:
    assert validate_take(good) == []


def test_wrong_dtype(good: Path, tmp_path: Path) -> None:
    probs = _corrupt(
        good, tmp_path, lambda f: _replace(f, "events/ev0/t", f["events/ev0/t"][:].astype(np.float64))
    )
    _one(probs, "/events/ev0/t", "dtype float64", "int64")


def test_unequal_lengths(good: Path, tmp_path: Path) -> None:
    probs = _corrupt(good, tmp_path, lambda f: _replace(f, "events/ev0/x", f["events/ev0/x"][:-3]))
    _one(probs, "/events/ev0", "unequal lengths")
    probs = _corrupt(
        good, tmp_path, lambda f: _replace(f, "frames/cam0/exposure_us", f["frames/cam0/exposure_us"][:-1])
    )
    _one(probs, "/frames/cam0", "unequal lengths", "exposure_us=8")


def test_non_monotonic_t(good: Path, tmp_path: Path) -> None:
    def edit(f: h5py.File) -> None:
        t = f["events/ev0/t"]
        t[12_345] = int(t[12_344]) - 5

    probs = _corrupt(good, tmp_path, edit)
    _one(probs, "/events/ev0/t", "decreases at index 12345")


def test_out_of_geometry_and_bad_polarity(good: Path, tmp_path: Path) -> None:
    def edit(f: h5py.File) -> None:
        f["events/ev0/y"][77] = 48
        f["events/ev0/p"][5] = 2

    probs = _corrupt(good, tmp_path, edit)
    _one(probs, "/events/ev0/y", "index 77", "height 48")
    _one(probs, "/events/ev0/p", "index 5")


def test_inconsistent_ms_to_idx(good: Path, tmp_path: Path) -> None:
    def edit(f: h5py.File) -> None:
        f["events/ev0/ms_to_idx"][100] = int(f["events/ev0/ms_to_idx"][100]) + 1

    _one(_corrupt(good, tmp_path, edit), "/events/ev0/ms_to_idx", "entry 100")
    probs = _corrupt(
        good, tmp_path, lambda f: _replace(f, "events/ev0/ms_to_idx", f["events/ev0/ms_to_idx"][:-1])
    )
    _one(probs, "/events/ev0/ms_to_idx", "entries")


def test_missing_attrs_and_datasets(good: Path, tmp_path: Path) -> None:
    def edit(f: h5py.File) -> None:
        del f.attrs["take_id"]
        del f["events/ev0"].attrs["width"]
        del f["trigger/pulses/t_us"]
        f.attrs["schema"] = "other.schema"

    probs = _corrupt(good, tmp_path, edit)
    _one(probs, ": /:", "take_id")
    _one(probs, "/events/ev0", "width")
    _one(probs, "/trigger/pulses/t_us", "missing")
    _one(probs, "schema", "other.schema")


def test_frame_times_and_report(good: Path, tmp_path: Path) -> None:
    def edit(f: h5py.File) -> None:
        f["frames/cam0/t_exposure_start_us"][4] = 0
        del f["sync/report_json"]
        f.create_dataset("sync/report_json", data='{"rate_hz": "fast"}', dtype=h5py.string_dtype())

    probs = _corrupt(good, tmp_path, edit)
    _one(probs, "/frames/cam0/t_exposure_start_us", "frame 4")
    _one(probs, "/sync/report_json", "SyncReport")


def test_complete_without_rig_time(good: Path, tmp_path: Path) -> None:
    probs = _corrupt(good, tmp_path, lambda f: f.attrs.__setitem__("time_domain", "device"))
    _one(probs, "time_domain")


def test_unreadable_file_is_one_problem(tmp_path: Path) -> None:
    p = tmp_path / "junk.h5"
    p.write_bytes(b"not an hdf5 file at all" * 100)
    probs = validate_take(p)
    assert len(probs) == 1
    assert str(p) in probs[0]
    assert "cannot be opened" in probs[0]
    assert validate_take(tmp_path / "missing.h5")[0].startswith(str(tmp_path / "missing.h5"))
    with pytest.raises(TakeError, match=r"junk\.h5"):
        open_take(p)


def test_never_finalized_take_opens_and_validates(tmp_path: Path) -> None:
    wr = make_take(tmp_path / "rec.h5", finalize=False)
    assert validate_take(wr.path) == []
    with open_take(wr.path) as take:
        assert take.status == "recording"
        assert take.time_domain == "device"


@pytest.mark.slow
def test_crash_after_flush_leaves_a_readable_take(tmp_path: Path) -> None:
    """A process killed after flush (no close) leaves everything flushed readable."""
    path = tmp_path / "crash.h5"
    script = textwrap.dedent(
        f"""
        import os, numpy as np
        from rigd.core.devices import DeviceInfo
        from rigd.core.settings import WriterConfig
        from rigd.core.events import EventArray
        from rigd.take import TakeWriter
        cfg = WriterConfig(event_chunk=1024)
        w = TakeWriter({str(path)!r}, rig_config_json="{{}}", take_id="c", config=cfg, rigd_version="t")
        w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="s"), 64, 48, "{{}}")
        n = 5000
        ev = EventArray.from_arrays(np.arange(n) % 64, np.arange(n) % 48, np.ones(n), np.arange(n))
        w.append_events("ev0", ev)
        w.flush()
        w.append_events("ev0", EventArray.from_arrays([1], [1], [1], [n + 10]))  # buffered, lost
        os._exit(3)
        """
    )
    proc = subprocess.run([sys.executable, "-c", script], cwd=Path(__file__).parents[3], check=False)
    assert proc.returncode == 3
    assert validate_take(path) == []
    with open_take(path) as take:
        assert take.status == "recording"
        np.testing.assert_array_equal(take.sensor("ev0").events().t, np.arange(5000))
