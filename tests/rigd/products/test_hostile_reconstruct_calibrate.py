"""Hostile inputs to `rigd reconstruct` and `rigd calibrate`: one line naming the problem, no traceback."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from firmware_sim.testing.takes import make_take
from rigd.app.cli import app
from rigd.products.reconstruct import run_reconstruct
from rigd.products.reconstruct_options import ReconstructOptions


def _good(d: Path, name: str = "good.h5") -> Path:
    return make_take(d / name, n_events=20_000).path


def _empty(d: Path) -> Path:
    (d / "empty.h5").write_bytes(b"")
    return d / "empty.h5"


def _text(d: Path) -> Path:
    (d / "notes.h5").write_text("not a take\n")
    return d / "notes.h5"


def _truncated(keep: float) -> Callable[[Path], Path]:
    def make(d: Path) -> Path:
        data = _good(d, "src.h5").read_bytes()
        (d / "trunc.h5").write_bytes(data[: int(len(data) * keep)])
        return d / "trunc.h5"

    return make


def _deleted(hpath: str) -> Callable[[Path], Path]:
    def make(d: Path) -> Path:
        dst = d / "deleted.h5"
        shutil.copy(_good(d, "src.h5"), dst)
        with h5py.File(dst, "r+") as f:
            del f[hpath]
        return dst

    return make


def _times(edit: Callable[[np.ndarray], np.ndarray]) -> Callable[[Path], Path]:
    def make(d: Path) -> Path:
        dst = d / "nonmono.h5"
        shutil.copy(_good(d, "src.h5"), dst)
        with h5py.File(dst, "r+") as f:
            t = f["events/ev0/t"]
            t[...] = edit(t[...].copy())
        return dst

    return make


def _swap_middle(t: np.ndarray) -> np.ndarray:
    i = len(t) // 2
    t[i], t[i + 1] = t[i + 1] + 5, t[i]
    return t


def _last_early(t: np.ndarray) -> np.ndarray:
    t[-1] = t[0]
    return t


HOSTILE = [
    (_empty, "cannot be opened"),
    (_text, "cannot be opened"),
    (_truncated(0.5), "truncated"),
    (_truncated(0.95), "truncated"),
    (_deleted("events/ev0/t"), "/events/ev0/t"),
    (_deleted("events/ev0/x"), "/events/ev0/x"),
    (_times(lambda t: t[::-1].copy()), "go backwards"),
    (_times(_swap_middle), "go backwards"),
    (_times(_last_early), "go backwards"),
]


@pytest.mark.parametrize(("make", "problem"), HOSTILE)
def test_unreadable_take_is_one_line_naming_it(
    tmp_path: Path, make: Callable[[Path], Path], problem: str
) -> None:
    bad = make(tmp_path)
    r = CliRunner().invoke(app, ["reconstruct", str(bad), "--out", str(tmp_path / "out")])
    assert r.exit_code in (1, 2), r.output
    assert "Traceback" not in r.output
    assert not isinstance(r.exception, Exception) or isinstance(r.exception, SystemExit), r.exception
    lines = r.output.strip().splitlines()
    assert len(lines) == 1, r.output
    assert str(bad) in lines[0]
    assert problem in lines[0]


@pytest.mark.parametrize(("make", "problem"), HOSTILE[::2])
def test_good_takes_are_reconstructed_beside_a_bad_one(
    tmp_path: Path, make: Callable[[Path], Path], problem: str
) -> None:
    (tmp_path / "bad").mkdir()
    bad = make(tmp_path / "bad")
    good = _good(tmp_path)
    out = tmp_path / "out"
    r = CliRunner().invoke(app, ["reconstruct", str(good), str(bad), str(good), "--out", str(out)])
    assert r.exit_code == 1, r.output
    assert "Traceback" not in r.output
    lines = r.output.strip().splitlines()
    errors = [ln for ln in lines if str(bad) in ln]
    assert len(errors) == 1, r.output
    assert problem in errors[0], r.output
    summaries = [ln for ln in lines if ln.startswith(f"{good}: ") and " segment" in ln]
    assert len(summaries) == 2, r.output
    assert all("ev0 kept" in ln for ln in summaries), r.output
    assert (out / "take-1" / "segments.json").is_file()


def test_workflow_returns_the_error_in_input_order(tmp_path: Path) -> None:
    good = _good(tmp_path)
    bad = _deleted("events/ev0/t")(tmp_path)
    results = run_reconstruct(ReconstructOptions(takes=[bad, good], out=tmp_path / "out"))
    assert [r.take for r in results] == [str(bad), str(good)]
    assert results[0].error is not None
    assert "/events/ev0/t" in results[0].error
    assert results[0].sensors == {}
    assert results[1].error is None
    assert results[1].sensors["ev0"].events_in == 20_000


def test_errors_raised_in_distributed_tasks_come_back_as_one_line(tmp_path: Path) -> None:
    distributed = pytest.importorskip("distributed")
    good = _good(tmp_path)
    makers = [_empty, _truncated(0.9), _times(_swap_middle)]
    bad = []
    for i, make in enumerate(makers):
        (tmp_path / str(i)).mkdir()
        bad.append(make(tmp_path / str(i)))
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
    ) as c:
        options = ReconstructOptions(takes=[*bad, good], out=tmp_path / "out", scheduler=c.scheduler_address)
        results = run_reconstruct(options)
    assert [r.take for r in results] == [str(p) for p in [*bad, good]]
    problems = ["cannot be opened", "truncated", "go backwards"]
    for path, r, problem in zip(bad, results[:-1], problems, strict=True):
        assert r.error is not None
        assert str(path) in r.error
        assert problem in r.error
        assert "\n" not in r.error
    assert results[-1].error is None
    assert results[-1].sensors["ev0"].events_in == 20_000


# --- rigd calibrate intrinsics with a miscounted board ---------------------------------------------

STEREO = Path("/work/shared/data/chessboard-stereo")
needs_stereo = pytest.mark.skipif(
    not (STEREO / "left01.jpg").is_file(), reason="chessboard-stereo data not available"
)


def _left() -> list[str]:
    return [str(p) for p in sorted(STEREO.glob("left*.jpg"))]


@needs_stereo
@pytest.mark.parametrize(
    ("spec", "shown"),
    [("8x6", "4 of 16 images show a 8x6 board"), ("9x7", "0 of 16 images show a 9x7 board"), ("10x6", "")],
)
@pytest.mark.slow
def test_wrong_corner_count_names_the_size_that_detects(tmp_path: Path, spec: str, shown: str) -> None:
    out = tmp_path / "cam.yaml"
    argv = ["calibrate", "intrinsics", *_left(), "--board", f"chessboard:{spec}:0.025", "--out", str(out)]
    r = CliRunner().invoke(app, argv)
    assert r.exit_code in (1, 2), r.output
    assert "Traceback" not in r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1, r.output
    assert shown in lines[0]
    assert f"show a {spec} board" in lines[0]
    assert "16 of 16 show 9x6: use --board chessboard:9x6:0.025" in lines[0]
    assert not out.exists()


@pytest.mark.slow
@needs_stereo
def test_allow_few_views_calibrates_from_the_views_found(tmp_path: Path) -> None:
    out = tmp_path / "cam.yaml"
    argv = ["calibrate", "intrinsics", *_left(), "--board", "chessboard:8x6:0.025", "--out", str(out)]
    r = CliRunner().invoke(app, [*argv, "--allow-few-views"])
    assert r.exit_code == 0, r.output
    assert "4 views" in r.output
    assert out.is_file()


@pytest.mark.slow
@needs_stereo
def test_few_views_and_no_nearby_size_refuses_in_one_line(tmp_path: Path) -> None:
    blank = np.full((512, 640, 3), 128, np.uint8)
    files = _left()[:3]
    for i in range(4):
        cv2.imwrite(str(tmp_path / f"blank{i}.png"), blank)
        files.append(str(tmp_path / f"blank{i}.png"))
    out = tmp_path / "cam.yaml"
    argv = ["calibrate", "intrinsics", *files, "--board", "chessboard:9x6:0.025", "--out", str(out)]
    r = CliRunner().invoke(app, argv)
    assert r.exit_code in (1, 2), r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1, r.output
    assert "3 of 7 images show a 9x6 board" in lines[0]
    assert "--allow-few-views" in lines[0]
    assert not out.exists()


# --- rigd calibrate events on a take without a board ------------------------------------------------


@pytest.mark.parametrize("methods", [[], ["-m", "hpf"], ["-m", "window", "-m", "integrate"]])
def test_events_take_without_a_board_is_refused_early_in_one_line(tmp_path: Path, methods: list[str]) -> None:
    take = make_take(tmp_path / "noboard.h5", n_events=40_000).path
    out = tmp_path / "ev0.yaml"
    argv = ["calibrate", "events", str(take), "--sensor", "ev0", "--board", "chessboard:9x6:0.025"]
    r = CliRunner().invoke(app, [*argv, "--out", str(out), *methods])
    assert r.exit_code in (1, 2), r.output
    assert "Traceback" not in r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1, r.output
    assert str(take) in lines[0]
    assert "not found in 8 frames" in lines[0]
    assert "scene=board" in lines[0]
    assert "sim://W/ev0?scene=board" in lines[0]
    assert not out.exists()
