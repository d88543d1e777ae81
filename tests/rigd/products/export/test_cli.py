"""`rigd export` on the command line: one clear line for each bad input, the summary line,
and the --segments hand-over from `rigd reconstruct`."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from rigd.app.cli import app
from rigd.take.reader import open_take

RES = (320, 180)
runner = CliRunner()


def _one_error_line(output: str) -> str:
    lines = [ln for ln in output.splitlines() if ln.strip()]
    assert len(lines) == 1, output
    assert lines[0].startswith("error:"), output
    return lines[0]


@pytest.mark.slow
def test_uncalibrated_take_is_refused_naming_the_command(takes: tuple[Path, Path], tmp_path: Path) -> None:
    raw, _ = takes
    r = runner.invoke(app, ["export", str(raw), "--format", "colmap", "--out", str(tmp_path / "o")])
    assert r.exit_code == 2
    line = _one_error_line(r.output)
    assert raw.name in line
    assert "rigd calibrate rig" in line
    assert "--into-take" in line
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    ("args", "expect"),
    [
        (["--format", "ply"], "unknown format"),
        (["--format", "colmap", "--resize", "big"], "expected WxH"),
        (["--format", "colmap", "--out-parent-missing"], "does not exist"),
        (["--format", "dsec", "--segments-missing"], "no such directory"),
    ],
)
@pytest.mark.slow
def test_bad_input_is_one_line(
    takes: tuple[Path, Path], tmp_path: Path, args: list[str], expect: str
) -> None:
    _, take = takes
    out = tmp_path / "o"
    if "--out-parent-missing" in args:
        args, out = args[:-1], tmp_path / "nowhere" / "o"
    if "--segments-missing" in args:
        args = [*args[:-1], "--segments", str(tmp_path / "no-recon")]
    r = runner.invoke(app, ["export", str(take), *args, "--out", str(out)])
    assert r.exit_code == 2, r.output
    assert expect in _one_error_line(r.output)


def test_camera_without_frames_is_one_line(takes: tuple[Path, Path], tmp_path: Path) -> None:
    _, take = takes
    empty = tmp_path / "empty.h5"
    shutil.copy(take, empty)
    with h5py.File(empty, "r+") as f:
        for name in (
            "images",
            "t_exposure_start_us",
            "t_exposure_start_device_us",
            "exposure_us",
            "frame_counter",
            "host_time_ns",
            "pulse_index",
        ):
            f[f"frames/cam2/{name}"].resize(0, axis=0)
    r = runner.invoke(app, ["export", str(empty), "--format", "nerfstudio", "--out", str(tmp_path / "o")])
    assert r.exit_code == 2, r.output
    assert "camera 'cam2' has no frames" in _one_error_line(r.output)


@pytest.mark.slow
def test_export_with_segments(takes: tuple[Path, Path], tmp_path: Path) -> None:
    """The segments.json of `rigd reconstruct` is carried, keyframes with their export time."""
    _, take = takes
    with open_take(take) as tk:
        take_id = tk.take_id
        t_mid = int(np.median(tk.camera("cam0").timestamps_us))
    recon = tmp_path / "recon"
    (recon / take_id / "ev0").mkdir(parents=True)
    seg = {
        "index": 0,
        "t_start_us": 0,
        "t_end_us": 10**6,
        "keyframe_us": t_mid,
        "n_events": 5,
        "activity": 0.1,
    }
    (recon / take_id / "ev0" / "segments.json").write_text(json.dumps({"segments": [seg]}))
    out = tmp_path / "o"
    r = runner.invoke(
        app, ["export", str(take), "--format", "nerfstudio", "--out", str(out), "--segments", str(recon)]
    )
    assert r.exit_code == 0, r.output
    assert "train" in r.output
    got = json.loads((out / "segments" / "ev0.json").read_text())["segments"][0]
    assert got["keyframe_us"] == t_mid
    assert 0.3 < got["keyframe_time"] < 0.7
    frames = json.loads((out / "transforms.json").read_text())["frames"]
    steps = {f["timestep"]: f["t_us"] for f in frames if f["camera"] == "cam0"}
    assert abs(steps[got["keyframe_step"]] - t_mid) <= 20_000


@pytest.mark.slow
def test_dynamic3dgs_seg_masks(takes: tuple[Path, Path], tmp_path: Path) -> None:
    _, take = takes
    out = tmp_path / "o"
    r = runner.invoke(app, ["export", str(take), "--format", "dynamic3dgs", "--out", str(out), "--seg"])
    assert r.exit_code == 0, r.output
    meta = json.loads((out / "train_meta.json").read_text())
    fn = meta["fn"][0][0]
    mask = cv2.imread(str(out / "seg" / fn.replace(".jpg", ".png")), cv2.IMREAD_UNCHANGED)
    assert mask is not None
    assert mask.shape == (RES[1], RES[0])
    assert np.all(mask == 1)
