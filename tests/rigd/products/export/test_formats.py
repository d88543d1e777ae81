# ruff: noqa: N806  (K, R, t follow the notation of the calibration literature)
"""`rigd export` on a short board-scene sim take, which carries its ground-truth calibration
from the capture (no calibration session).

Every format is read back with a reader written here from the format's documentation (pycolmap
for COLMAP), never with the writer's code, and the sim's ground-truth 3-D board corners, at each
frame's true mid-exposure, are projected with the exported cameras onto the corners detected
in the exported images, in the consumer's own pixel convention: COLMAP, nerfstudio and the
Gaussian rasterizers centre pixel (0, 0) at (0.5, 0.5), so a corner that OpenCV finds at u is
at u + 0.5 for them. The ground-truth calibration makes this a test of the export's conventions
(axes, K after undistortion and resizing, pixel centres, which frame at which time).
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import h5py
import hdf5plugin  # noqa: F401  (voxels.h5 is Zstd-compressed)
import numpy as np
import pycolmap
import pytest
from numpy.typing import NDArray

from firmware_sim.board_scene import BoardScene
from firmware_sim.testing.board import true_mid_exposures
from firmware_sim.world import get_world
from rigd.app.testing.board import capture_board_take
from rigd.core.progress import ProgressUpdate, no_progress
from rigd.products.export import ExportOptions, run_export
from rigd.take.calibration import GROUND_TRUTH_SOURCE, store_calibration
from rigd.take.reader import open_take
from tests.rigd.products.export.dsec_checks import check_dsec_events

pytestmark = pytest.mark.slow

RES = (480, 270)
WORLD = "t-export"
F64 = NDArray[np.float64]


@dataclass
class View:
    """One exported image as an independent reader sees it."""

    camera: str
    image: Path
    K: F64
    w2c: F64  # 4x4, OpenCV axes
    t_us: int
    centre: float = 0.0
    """Where the consumer centres pixel (0, 0): 0 (OpenCV, DSEC) or 0.5 (COLMAP, nerfstudio, 3DGS)."""


@dataclass
class Fixture:
    take: Path
    scene: BoardScene
    truth_us: dict[str, dict[int, float]]  # camera -> rig mid-exposure us -> true render time
    out: dict[str, Path]
    progress: list[ProgressUpdate]


def _store_dist(take: Path, dist: list[float]) -> None:
    """The take's stored ground truth with a lens distortion added to every device."""
    with open_take(take) as tk:
        calib = tk.calibration
    assert calib is not None
    for d, c in calib.items():
        intr = {"K": c["K"].tolist(), "dist": dist, "image_size": c["image_size"].tolist()}
        store_calibration(take, d, intr, {"R": c["R"].tolist(), "t": c["t"].tolist()}, source="test")


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> Fixture:
    root = tmp_path_factory.mktemp("export")
    cap = capture_board_take(root / "take", 1.0, RES, world=WORLD, clock="virtual")
    scene = get_world(WORLD).resource("scene", BoardScene)
    assert isinstance(scene, BoardScene)
    out = {}
    updates: list[ProgressUpdate] = []
    for fmt in ("dynamic3dgs", "4dgaussians", "nerfstudio", "colmap", "dsec"):
        out[fmt] = root / fmt
        callback = updates.append if fmt == "dsec" else no_progress
        # the sim's world (the board plane): the ground-truth corners are in it
        run_export(ExportOptions(take=cap.path, format=fmt, out=out[fmt], world="board"), callback)
    out["resized"] = root / "resized"
    run_export(
        ExportOptions(
            take=cap.path, format="nerfstudio", out=out["resized"], resize=(384, 216), world="board"
        )
    )
    return Fixture(cap.path, scene, true_mid_exposures(cap.path, WORLD), out, updates)


# --- independent readers ------------------------------------------------------------------


def read_dynamic3dgs(root: Path) -> dict[str, list[View]]:
    """PanopticSports metas (Dynamic3DGaussians, 4DGaussians): pixel centres at +0.5."""
    out = {}
    for split in ("train", "test"):
        meta = json.loads((root / f"{split}_meta.json").read_text())
        views = []
        for t, fns in enumerate(meta["fn"]):
            for c, fn in enumerate(fns):
                name = meta["cam_name"][t][c]
                K, w2c = np.array(meta["k"][t][c]), np.array(meta["w2c"][t][c])
                views.append(View(name, root / "ims" / fn, K, w2c, int(meta["t_us"][t][c]), 0.5))
        out[split] = views
    return out


def read_nerfstudio(root: Path) -> dict[str, list[View]]:
    meta = json.loads((root / "transforms.json").read_text())
    assert meta["camera_model"] == "PINHOLE"
    out: dict[str, list[View]] = {"train": [], "test": []}
    for fr in meta["frames"]:
        K = np.array([[fr["fl_x"], 0, fr["cx"]], [0, fr["fl_y"], fr["cy"]], [0, 0, 1]])
        c2w_cv = np.array(fr["transform_matrix"]) @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL -> OpenCV
        split = "train" if fr["file_path"] in set(meta["train_filenames"]) else "test"
        out[split].append(
            View(fr["camera"], root / fr["file_path"], K, np.linalg.inv(c2w_cv), fr["t_us"], 0.5)
        )
    return out


def read_colmap(root: Path) -> dict[str, list[View]]:
    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    times = json.loads((root / "times.json").read_text())
    out: dict[str, list[View]] = {"train": [], "test": []}
    for im in rec.images.values():
        cam = rec.cameras[im.camera_id]
        fx, fy, cx, cy = cam.params
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
        pose = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        w2c = np.eye(4)
        w2c[:3, :] = pose.matrix()
        info = times[im.name]
        out[info["split"]].append(
            View(im.name.split("/")[0], root / "images" / im.name, K, w2c, info["t_us"], 0.5)
        )
    return out


def read_dsec_frames(root: Path) -> list[View]:
    calib = json.loads((root / "calibration" / "cameras.json").read_text())["devices"]
    origin = json.loads((root / "split.json").read_text())["rig_time_origin_us"]
    views = []
    for cam_dir in sorted((root / "images").iterdir()):
        d = calib[cam_dir.name]
        stamps = [int(s) + origin for s in (cam_dir / "timestamps.txt").read_text().split()]
        files = sorted((cam_dir / "rectified").glob("*.png"))
        assert len(files) == len(stamps)
        for f, t in zip(files, stamps, strict=True):
            views.append(View(cam_dir.name, f, np.array(d["K_rect"]), np.array(d["T_cam_world"]), t))
    return views


# --- the projection check -----------------------------------------------------------------


def _refine(gray: NDArray[Any], corners: NDArray[Any], pattern: tuple[int, int]) -> F64:
    """cornerSubPix with a window below half the corner spacing: a wider one pulls neighbouring
    corners of a small or steeply tilted board together."""
    grid = corners.reshape(pattern[1], pattern[0], 2)
    spacing = min(
        float(np.linalg.norm(np.diff(grid, axis=1), axis=2).min()),
        float(np.linalg.norm(np.diff(grid, axis=0), axis=2).min()),
    )
    win = int(np.clip(np.floor(spacing * 0.4), 2, 5))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    return cv2.cornerSubPix(gray, corners, (win, win), (-1, -1), crit).reshape(-1, 2).astype(np.float64)


def _detect(path: Path, pattern: tuple[int, int]) -> F64 | None:
    gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert gray is not None, path
    ok, corners = cv2.findChessboardCorners(gray, pattern)
    return _refine(gray, corners, pattern) if ok else None


def projection_errors(fx: Fixture, views: list[View]) -> tuple[F64, F64, int]:
    """Per-view mean distance (px) between the projected ground-truth corners and the detected
    ones in the consumer's pixels (OpenCV's + the view's `centre`), the mean residual (x, y) over
    every corner, and how many views were checked (the board must be fully visible)."""
    scene = fx.scene
    pattern = (scene.cols, scene.rows)
    errs, residuals = [], []
    for v in views:
        found = _detect(v.image, pattern)
        if found is None:
            continue
        found = found + v.centre
        R_b, t_b = scene.board_pose(fx.truth_us[v.camera][v.t_us])
        X = scene.board_points() @ R_b.T + t_b
        xc = X @ v.w2c[:3, :3].T + v.w2c[:3, 3]
        uv = xc @ v.K.T
        uv = uv[:, :2] / uv[:, 2:3]
        # The detector may report the corners in the reverse order (180-degree ambiguity).
        if np.linalg.norm(found[::-1] - uv, axis=1).mean() < np.linalg.norm(found - uv, axis=1).mean():
            found = found[::-1]
        errs.append(np.linalg.norm(found - uv, axis=1).mean())
        residuals.append(uv - found)
    bias = np.concatenate(residuals).mean(axis=0) if residuals else np.full(2, np.nan)
    return np.array(errs), bias, len(errs)


def _check(fx: Fixture, views: list[View], label: str) -> None:
    errs, bias, n = projection_errors(fx, views)
    print(
        f"{label}: {n}/{len(views)} views with the board, mean {errs.mean():.3f} px, "
        f"max {errs.max():.3f} px, bias ({bias[0]:+.3f}, {bias[1]:+.3f}) px"
    )
    assert n >= len(views) // 3, (label, n, len(views))
    assert float(errs.max()) < 0.5, (label, errs)
    # Half a pixel off (a principal point in the wrong convention) is a bias of 0.5 in x and y.
    assert np.all(np.abs(bias) < 0.15), (label, bias)


READERS = {
    "dynamic3dgs": read_dynamic3dgs,
    "4dgaussians": read_dynamic3dgs,
    "nerfstudio": read_nerfstudio,
    "colmap": read_colmap,
}


def test_sim_take_carries_its_ground_truth(exported: Fixture) -> None:
    """The capture stored the simulator's truth (no calibration session ran): every device, in
    the rig frame of cam0, and the board plane's pose."""
    with open_take(exported.take) as tk:
        calib = tk.calibration
        assert calib is not None
        assert set(calib) == set(tk.cameras + tk.event_sensors)
        _, R0, t0 = exported.scene.view_camera("cam0", *RES)
        for dev, c in calib.items():
            assert c["result"]["source"] == GROUND_TRUTH_SOURCE
            K, R, t = exported.scene.view_camera(dev, *RES)
            np.testing.assert_allclose(c["K"], K)
            np.testing.assert_allclose(c["R"], R @ R0.T, atol=1e-12)
            np.testing.assert_allclose(-c["R"].T @ c["t"], R0 @ (-R.T @ t) + t0, atol=1e-12)
        board = tk.board_pose
        assert board is not None
        np.testing.assert_allclose(board[0], R0)
        np.testing.assert_allclose(board[1], t0)


@pytest.mark.parametrize("fmt", ["dynamic3dgs", "4dgaussians", "nerfstudio", "colmap"])
def test_trainer_format_projects_ground_truth(exported: Fixture, fmt: str) -> None:
    views = READERS[fmt](exported.out[fmt])
    if fmt in ("dynamic3dgs", "4dgaussians"):  # split by camera: cam1 held out at every timestep
        assert (len(views["train"]), len(views["test"])) == (60, 30)
        assert {v.camera for v in views["test"]} == {"cam1"}
    else:
        assert {len(views["train"]), len(views["test"])} == {45}  # 30 timesteps x 3 cameras, half each
    _check(exported, views["train"] + views["test"], fmt)


def test_the_pixel_centre_check_catches_half_a_pixel(exported: Fixture) -> None:
    """The check above fails when the consumer's +0.5 is left out (as rigd wrote it before)."""
    views = read_colmap(exported.out["colmap"])["train"]
    for v in views:
        v.centre = 0.0
    with pytest.raises(AssertionError):
        _check(exported, views, "colmap read as OpenCV pixels")


def test_dsec_frames_project_ground_truth(exported: Fixture) -> None:
    _check(exported, read_dsec_frames(exported.out["dsec"]), "dsec")


def test_resized_intrinsics_project_ground_truth(exported: Fixture) -> None:
    views = read_nerfstudio(exported.out["resized"])
    all_views = views["train"] + views["test"]
    first = cv2.imread(str(all_views[0].image))
    assert first is not None
    assert first.shape[:2] == (216, 384)
    _check(exported, all_views, "nerfstudio 384x216")


def test_split_is_even_train_odd_test(exported: Fixture) -> None:
    views = read_nerfstudio(exported.out["nerfstudio"])
    t_train = sorted({v.t_us for v in views["train"] if v.camera == "cam0"})
    t_test = sorted({v.t_us for v in views["test"] if v.camera == "cam0"})
    merged = sorted(t_train + t_test)
    assert t_train == merged[0::2]
    assert t_test == merged[1::2]
    # 30 FPS: about 33 333 us between frames, 66 667 between training frames
    assert np.allclose(np.diff(t_train), 66_667, atol=300), np.diff(t_train)


def test_trainer_formats_agree(exported: Fixture) -> None:
    """Same camera centres (1e-6 m) and the same times in the three trainer formats."""
    readers = READERS
    centres: dict[str, dict[str, F64]] = {}
    times: dict[str, dict[tuple[str, str], int]] = {}
    for fmt, reader in readers.items():
        views = reader(exported.out[fmt])
        centres[fmt] = {}
        times[fmt] = {}
        for split, vs in views.items():
            for v in vs:
                c = -v.w2c[:3, :3].T @ v.w2c[:3, 3]
                if v.camera in centres[fmt]:
                    assert np.allclose(centres[fmt][v.camera], c, atol=1e-9)
                centres[fmt][v.camera] = c
                times[fmt][(v.camera, v.image.stem)] = v.t_us
                assert split in ("train", "test")
    ref = centres["nerfstudio"]
    with open_take(exported.take) as tk:
        for cam in tk.cameras:
            _, R, t = exported.scene.view_camera(cam, *RES)  # --world board: the sim's world
            truth = -R.T @ t
            for fmt in readers:
                assert np.linalg.norm(centres[fmt][cam] - ref[cam]) < 1e-6, (fmt, cam)
            assert np.linalg.norm(ref[cam] - truth) < 1e-6, cam
    assert times["nerfstudio"] == times["colmap"] == times["dynamic3dgs"]
    # normalized time: [0, 1] over the exported frames, the same in the D-NeRF files
    dnerf = [
        f
        for s in ("train", "test")
        for f in json.loads((exported.out["nerfstudio"] / f"transforms_{s}.json").read_text())["frames"]
    ]
    assert min(f["time"] for f in dnerf) == 0.0
    assert max(f["time"] for f in dnerf) == 1.0


def test_initial_point_clouds(exported: Fixture) -> None:
    """Dynamic3DGaussians' init_pt_cld (N x 7) and COLMAP's points3D hold the same triangulated
    points, in front of every camera that saw them and on the scene (within the board's reach)."""
    data = np.load(exported.out["dynamic3dgs"] / "init_pt_cld.npz")["data"]
    assert data.ndim == 2
    assert data.shape[1] == 7
    assert len(data) >= 10
    assert np.all((data[:, 3:6] >= 0) & (data[:, 3:6] <= 1))
    assert np.all(data[:, 6] == 1)
    rec = pycolmap.Reconstruction(str(exported.out["colmap"] / "sparse" / "0"))
    xyz = np.array([p.xyz for p in rec.points3D.values()])
    assert len(xyz) == len(data)
    assert np.allclose(np.sort(xyz, axis=0), np.sort(data[:, :3], axis=0), atol=1e-9)
    for p in rec.points3D.values():
        assert p.track.length() == 2
        assert p.error < 1.0


# --- events -------------------------------------------------------------------------------


def test_dsec_events_match_the_take(exported: Fixture) -> None:
    check_dsec_events(exported.out["dsec"], exported.take, RES)


def test_voxel_grids_hold_each_frames_events(exported: Fixture) -> None:
    root = exported.out["nerfstudio"]
    with open_take(exported.take) as tk:
        for sensor in tk.event_sensors:
            with h5py.File(root / "events" / sensor / "voxels.h5", "r") as f:
                vox, win = f["voxels"], f["window_us"][()]
                assert vox.shape == (30, 5, RES[1], RES[0])
                for k in (0, 7, 29):
                    a, b = int(win[k, 0]), int(win[k, 1])
                    ev = tk.sensor(sensor).events(a + 1, b + 1)  # the window is (a, b]
                    # bilinear weights in time sum to 1: the grid sums to the polarity sum
                    assert abs(float(vox[k].sum()) - float(ev.p.sum())) < 1e-2 * max(len(ev), 1)
                    counts = np.zeros((RES[1], RES[0]))
                    np.add.at(counts, (ev.y, ev.x), ev.p)
                    np.testing.assert_allclose(vox[k].sum(axis=0), counts, atol=1e-4)
            calib = json.loads((root / "events" / sensor / "calibration.json").read_text())
            assert np.allclose(calib["K"], tk.calibration[sensor]["K"])  # type: ignore[index]


# --- undistortion round trip --------------------------------------------------------------


def test_nonzero_dist_round_trip(exported: Fixture, tmp_path: Path) -> None:
    """A stored non-zero dist undistorts the frames with the new pinhole K: the corners detected
    in the exported image sit where cv2.undistortPoints(K, dist, P=K_new) puts the corners
    detected in the take's own frame."""
    take = tmp_path / "take.h5"
    shutil.copy(exported.take, take)
    dist = [-0.08, 0.02, 0.001, -0.0005, 0.0]
    _store_dist(take, dist)
    out = tmp_path / "out"
    run_export(ExportOptions(take=take, format="nerfstudio", out=out, world="board"))
    views = read_nerfstudio(out)
    pattern = (exported.scene.cols, exported.scene.rows)
    checked = []
    with open_take(take) as tk:
        K = tk.calibration["cam1"]["K"]  # type: ignore[index]
        fs = tk.camera("cam1")
        mids = fs.timestamps_us + np.array([fs[i].exposure_us // 2 for i in range(len(fs))])
        for v in (v for v in views["train"] if v.camera == "cam1"):
            K_cv = v.K.copy()  # back to OpenCV's pixel centres
            K_cv[:2, 2] -= v.centre
            assert abs(K_cv[0, 2] - (RES[0] - 1) / 2) < 1e-6  # centred principal point
            i = int(np.flatnonzero(mids == v.t_us)[0])
            raw = np.asarray(fs[i].image, np.uint8)
            ok, c0 = cv2.findChessboardCorners(raw, pattern)
            exp = _detect(v.image, pattern)
            if not ok or exp is None:
                continue
            und = cv2.undistortPoints(_refine(raw, c0, pattern), K, np.array(dist), P=K_cv).reshape(-1, 2)
            e = min(np.linalg.norm(und - exp, axis=1).mean(), np.linalg.norm(und[::-1] - exp, axis=1).mean())
            checked.append(e)
    print(f"dist round trip: {len(checked)} views, max {max(checked):.3f} px")
    assert len(checked) >= 5
    assert max(checked) < 0.5


def test_progress_counts_up_to_each_stage_total(exported: Fixture) -> None:
    stages: dict[str, list[ProgressUpdate]] = {}
    for u in exported.progress:
        stages.setdefault(u.stage, []).append(u)
    assert {"images", "events ev0", "events ev1", "voxels ev0", "voxels ev1"} <= set(stages), stages.keys()
    images = stages["images"]
    assert images[0].done == 0
    assert images[-1].done == images[-1].total == 90
    done = [u.done for u in images]
    assert done == sorted(d for d in done if d is not None)
    assert stages["voxels ev0"][-1].done == 30
