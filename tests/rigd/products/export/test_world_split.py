# ruff: noqa: N806  (R, t follow the notation of the calibration literature)
"""`rigd export --world`, `--split` and DSEC's times on a take whose box clock is past 2^32 us."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from firmware_sim.board_scene import BoardScene
from firmware_sim.world import get_world
from rigd.app.capture import run_capture
from rigd.app.config import RigConfig
from rigd.app.testing.board import board_rig
from rigd.core.errors import ConfigError, TakeError
from rigd.products.export import ExportOptions, run_export
from tests.rigd.products.export.dsec_checks import check_dsec_events

RES = (320, 180)


def _meta_centres(root: Path) -> dict[str, np.ndarray]:
    """Camera centres (world) of a PanopticSports export, by camera name."""
    out = {}
    for split in ("train", "test"):
        meta = json.loads((root / f"{split}_meta.json").read_text())
        for names, w2cs in zip(meta["cam_name"], meta["w2c"], strict=True):
            for name, w2c in zip(names, w2cs, strict=True):
                m = np.array(w2c)
                out[name] = -m[:3, :3].T @ m[:3, 3]
    return out


@pytest.mark.slow
def test_world_board_is_the_scene_plane(takes: tuple[Path, Path], tmp_path: Path) -> None:
    """--world board: every camera where the simulator put it in its world (the board plane)."""
    _, take = takes
    run_export(ExportOptions(take=take, format="4dgaussians", out=tmp_path / "b", world="board"))
    scene = get_world("t-export-cli").resource("scene", BoardScene)
    for name, c in _meta_centres(tmp_path / "b").items():
        _, R, t = scene.view_camera(name, *RES)
        np.testing.assert_allclose(c, -R.T @ t, atol=1e-9)


@pytest.mark.slow
def test_world_floor_is_gravity_aligned_with_every_point_above_the_floor(
    takes: tuple[Path, Path], tmp_path: Path
) -> None:
    """dynamic3dgs defaults to --world floor: y along the board's down axis, the floor y = 0 at
    the lowest initial point, so Dynamic3DGaussians' clamp(y, min=0) floor loss starts at zero."""
    _, take = takes
    out = tmp_path / "f"
    result = run_export(ExportOptions(take=take, format="dynamic3dgs", out=out))
    assert result.world.startswith("floor")
    pts = np.load(out / "init_pt_cld.npz")["data"][:, :3]
    assert pts[:, 1].max() == pytest.approx(0.0, abs=1e-9)
    assert float(np.clip(pts[:, 1], 0, None).mean()) == 0.0
    # The cameras' height differences match the sim world's (y is the same axis up to a shift).
    scene = get_world("t-export-cli").resource("scene", BoardScene)
    centres = _meta_centres(out)
    truth = {n: -scene.view_camera(n, *RES)[1].T @ scene.view_camera(n, *RES)[2] for n in centres}
    dy = centres["cam2"][1] - centres["cam0"][1]
    assert dy == pytest.approx(truth["cam2"][1] - truth["cam0"][1], abs=1e-9)
    d = np.linalg.norm(centres["cam2"] - centres["cam0"])
    assert d == pytest.approx(np.linalg.norm(truth["cam2"] - truth["cam0"]), abs=1e-9)
    assert (out / "seg" / "0" / "000000.png").is_file()  # its loader opens seg/ for every image


def test_world_board_needs_a_board(takes: tuple[Path, Path], tmp_path: Path) -> None:
    bare, take = takes
    with h5py.File(take, "r") as f, h5py.File(bare, "r+") as g:  # calibration without the board
        f.copy("calibration", g)
        for k in ("board_R", "board_t", "board_source"):
            del g["calibration"].attrs[k]
    try:
        with pytest.raises(TakeError, match="--world board needs the board plane"):
            run_export(ExportOptions(take=bare, format="colmap", out=tmp_path / "o", world="board"))
        assert not (tmp_path / "o").exists()
    finally:
        with h5py.File(bare, "r+") as g:
            del g["calibration"]


@pytest.mark.slow
def test_split_camera_holds_out_a_camera_at_every_timestep(takes: tuple[Path, Path], tmp_path: Path) -> None:
    _, take = takes
    out = tmp_path / "s"
    run_export(ExportOptions(take=take, format="nerfstudio", out=out, split="camera", test_cameras=("cam2",)))
    meta = json.loads((out / "transforms.json").read_text())
    test = [f for f in meta["frames"] if f["split"] == "test"]
    assert {f["camera"] for f in test} == {"cam2"}
    assert meta["val_filenames"] == meta["test_filenames"] == [f["file_path"] for f in test]
    train_steps = {f["timestep"] for f in meta["frames"] if f["split"] == "train"}
    assert train_steps == {f["timestep"] for f in test}
    for split, cams, why in (
        ("camera", ("nope",), "--test-camera nope: not a camera"),
        ("camera", ("cam0", "cam1", "cam2"), "nothing to train on"),
        ("time", ("cam0",), "needs --split camera"),
    ):
        opts = ExportOptions(
            take=take, format="nerfstudio", out=tmp_path / "x", split=split, test_cameras=cams
        )
        with pytest.raises(ConfigError, match=why):
            run_export(opts)
        assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_split_time_in_panoptic_layout(takes: tuple[Path, Path], tmp_path: Path) -> None:
    _, take = takes
    out = tmp_path / "t"
    run_export(ExportOptions(take=take, format="4dgaussians", out=out, split="time"))
    train = json.loads((out / "train_meta.json").read_text())
    test = json.loads((out / "test_meta.json").read_text())
    assert all(k % 2 == 0 for k in train["timestep"])
    assert all(k % 2 == 1 for k in test["timestep"])
    assert all(len(fns) == 3 for fns in train["fn"] + test["fn"])


@pytest.fixture(scope="module")
def late_take(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A take whose trigger box (the rig clock) was powered on 5000 s earlier: rig us > 2^32."""
    data = board_rig("t-export-late", RES, clock="virtual").model_dump()
    data["trigger"]["spec"] += "&offset_us=5000000000"
    cap = run_capture(RigConfig.model_validate(data), tmp_path_factory.mktemp("late"), 0.5)
    return cap.path


@pytest.mark.slow
def test_dsec_times_past_2_32_us(late_take: Path, tmp_path: Path) -> None:
    """Rig times past 2^32 us: t_offset stays under 1 ms (times count from the take's start),
    so EventSlicer's uint32 `t + t_offset` neither wraps nor overflows."""
    out = tmp_path / "d"
    result = run_export(ExportOptions(take=late_take, format="dsec", out=out))
    assert result.t0_us > 2**32
    origin = json.loads((out / "split.json").read_text())["rig_time_origin_us"]
    assert origin > 2**32
    check_dsec_events(out, late_take, RES)
