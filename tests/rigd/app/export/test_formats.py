# ruff: noqa: N806  (K, R, t follow the notation of the calibration literature)
"""`rigd export` on a short board-scene sim take with its ground-truth calibration stored.

Every format is read back with a reader written here from the format's documentation (pycolmap
for COLMAP), never with the writer's code, and the sim's ground-truth 3-D board corners, at each
frame's true mid-exposure, are projected with the exported cameras onto the corners detected
in the exported images. The ground-truth calibration makes this a test of the export's
conventions (axes, K after undistortion and resizing, which frame at which time), not of calibration.
"""

from __future__ import annotations

import json
import math
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

from bench.e2calib import capture_board_take
from firmware_sim.board_scene import BoardScene
from firmware_sim.world import get_world
from rigd.app.export import ExportOptions, run_export
from rigd.app.workflows.progress import ProgressUpdate, no_progress
from rigd.take.calibration import store_calibration
from rigd.take.reader import open_take

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


@dataclass
class Fixture:
    take: Path
    scene: BoardScene
    truth_us: dict[str, dict[int, float]]  # camera -> rig mid-exposure us -> true render time
    out: dict[str, Path]
    progress: list[ProgressUpdate]


def _truth_times(take: Path) -> dict[str, dict[int, float]]:
    """Rig mid-exposure time of every frame -> the sim's true render time (mid-exposure)."""
    rows = get_world(WORLD).truth.frames
    out: dict[str, dict[int, float]] = {}
    with open_take(take) as tk, h5py.File(take, "r") as f:
        for cam in tk.cameras:
            true_start = {int(c): t for c, t, ok in rows[cam] if ok}
            counters = f[f"frames/{cam}/frame_counter"][()]
            exp = f[f"frames/{cam}/exposure_us"][()]
            mid = tk.frames(cam).timestamps_us + exp // 2
            out[cam] = {
                int(m): true_start[int(c)] + float(e) / 2 for m, c, e in zip(mid, counters, exp, strict=True)
            }
    return out


def _store_truth(take: Path, scene: BoardScene, dist: list[float] | None = None) -> None:
    with open_take(take) as tk:
        devices = tk.cameras + tk.event_sensors
    for d in devices:
        K, R, t = scene.view_camera(d, *RES)
        intr = {"K": K.tolist(), "dist": dist or [0.0] * 5, "image_size": list(RES)}
        store_calibration(take, d, intr, {"R": R.tolist(), "t": t.tolist()}, source="sim ground truth")


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> Fixture:
    root = tmp_path_factory.mktemp("export")
    cap = capture_board_take(root / "take", 1.0, RES, world=WORLD, clock="virtual")
    scene = get_world(WORLD).resource("scene", BoardScene)
    assert isinstance(scene, BoardScene)
    _store_truth(cap.path, scene)
    out = {}
    updates: list[ProgressUpdate] = []
    for fmt in ("dynamic3dgs", "nerfstudio", "colmap", "dsec"):
        out[fmt] = root / fmt
        callback = updates.append if fmt == "dsec" else no_progress
        run_export(ExportOptions(take=cap.path, format=fmt, out=out[fmt]), callback)
    out["resized"] = root / "resized"
    run_export(ExportOptions(take=cap.path, format="nerfstudio", out=out["resized"], resize=(384, 216)))
    return Fixture(cap.path, scene, _truth_times(cap.path), out, updates)


# --- independent readers ------------------------------------------------------------------


def read_dynamic3dgs(root: Path) -> dict[str, list[View]]:
    out = {}
    for split in ("train", "test"):
        meta = json.loads((root / f"{split}_meta.json").read_text())
        views = []
        for t, fns in enumerate(meta["fn"]):
            for c, fn in enumerate(fns):
                name = meta["cam_name"][meta["cam_id"][t][c]]
                K, w2c = np.array(meta["k"][t][c]), np.array(meta["w2c"][t][c])
                views.append(View(name, root / "ims" / fn, K, w2c, int(meta["t_us"][t][c])))
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
        out[split].append(View(fr["camera"], root / fr["file_path"], K, np.linalg.inv(c2w_cv), fr["t_us"]))
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
            View(im.name.split("/")[0], root / "images" / im.name, K, w2c, info["t_us"])
        )
    return out


def read_4dgaussians_multiview(root: Path) -> list[View]:
    """As 4DGaussians' scene/multipleview_dataset.py reads it: sparse_ poses, one focal length
    (camera 1's) with the principal point at the image centre, cam<NN>/frame_<i+1>.jpg."""
    rec = pycolmap.Reconstruction(str(root / "sparse_"))
    cam1 = rec.cameras[1]
    f, w, h = cam1.params[0], cam1.width, cam1.height
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    times = json.loads((root / "times.json").read_text())
    cam_names = sorted({k.split("/")[0] for k in times})
    views = []
    for im in rec.images.values():
        number = im.name[5:-4]
        folder = root / f"cam{number.zfill(2)}"
        pose = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        w2c = np.eye(4)
        w2c[:3, :] = pose.matrix()
        n = len(list(folder.iterdir()))
        for i in range(n):
            # the frame's time from the export's own times (the loader uses i / n)
            cam_name = cam_names[int(number) - 1]
            info = times[f"{cam_name}/{i:06d}.jpg"]
            views.append(View(cam_name, folder / f"frame_{i + 1:05d}.jpg", K, w2c, info["t_us"]))
    return views


def read_dsec_frames(root: Path) -> list[View]:
    calib = json.loads((root / "calibration" / "cameras.json").read_text())["devices"]
    views = []
    for cam_dir in sorted((root / "images").iterdir()):
        d = calib[cam_dir.name]
        stamps = [int(s) for s in (cam_dir / "timestamps.txt").read_text().split()]
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


def projection_errors(fx: Fixture, views: list[View]) -> tuple[F64, int]:
    """Per-view mean distance (px) between the projected ground-truth corners and the detected
    ones; and how many views were checked (the board must be fully visible)."""
    scene = fx.scene
    pattern = (scene.cols, scene.rows)
    errs = []
    for v in views:
        found = _detect(v.image, pattern)
        if found is None:
            continue
        R_b, t_b = scene.board_pose(fx.truth_us[v.camera][v.t_us])
        X = scene.board_points() @ R_b.T + t_b
        xc = X @ v.w2c[:3, :3].T + v.w2c[:3, 3]
        uv = xc @ v.K.T
        uv = uv[:, :2] / uv[:, 2:3]
        # The detector may report the corners in the reverse order (180-degree ambiguity).
        e = min(np.linalg.norm(found - uv, axis=1).mean(), np.linalg.norm(found[::-1] - uv, axis=1).mean())
        errs.append(e)
    return np.array(errs), len(errs)


def _check(fx: Fixture, views: list[View], label: str) -> None:
    errs, n = projection_errors(fx, views)
    print(
        f"{label}: {n}/{len(views)} views with the board, mean {errs.mean():.3f} px, max {errs.max():.3f} px"
    )
    assert n >= len(views) // 3, (label, n, len(views))
    assert float(errs.max()) < 0.5, (label, errs)


@pytest.mark.parametrize("fmt", ["dynamic3dgs", "nerfstudio", "colmap"])
def test_trainer_format_projects_ground_truth(exported: Fixture, fmt: str) -> None:
    reader = {"dynamic3dgs": read_dynamic3dgs, "nerfstudio": read_nerfstudio, "colmap": read_colmap}[fmt]
    views = reader(exported.out[fmt])
    assert {len(views["train"]), len(views["test"])} == {45}  # 30 timesteps x 3 cameras, half each
    _check(exported, views["train"] + views["test"], fmt)


def test_4dgaussians_multiview_tree_projects_ground_truth(exported: Fixture) -> None:
    views = read_4dgaussians_multiview(exported.out["colmap"])
    assert len(views) == 90
    _check(exported, views, "4dgaussians multiview")
    poses = np.load(exported.out["colmap"] / "poses_bounds_multipleview.npy")
    assert poses.shape == (3, 17)
    near, far = poses[:, -2].min(), poses[:, -1].max()
    assert 0 < near < far


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
    readers = {"dynamic3dgs": read_dynamic3dgs, "nerfstudio": read_nerfstudio, "colmap": read_colmap}
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
        calib = tk.calibration
        assert calib is not None
        for cam in tk.cameras:
            truth = -calib[cam]["R"].T @ calib[cam]["t"]
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


def _slice_dsec(path: Path, t0_us: int, t1_us: int) -> dict[str, NDArray[np.generic]]:
    """Events in [t0, t1) (absolute rig us) the way DSEC's EventSlicer finds them: ms_to_idx to a
    conservative index range, then the exact edges in t."""
    with h5py.File(path, "r") as f:
        off = int(f["t_offset"][()])
        ms = f["ms_to_idx"][()]
        a, b = t0_us - off, t1_us - off
        lo, hi = int(ms[math.floor(a / 1000)]), int(ms[math.ceil(b / 1000)])
        t = f["events/t"][lo:hi].astype(np.int64)
        i, j = lo + np.searchsorted(t, a, "left"), lo + np.searchsorted(t, b, "left")
        return {
            "t": f["events/t"][i:j].astype(np.int64) + off,
            "x": f["events/x"][i:j],
            "y": f["events/y"][i:j],
            "p": f["events/p"][i:j],
        }


def test_dsec_events_match_the_take(exported: Fixture) -> None:
    root = exported.out["dsec"]
    stamps = [int(s) for s in (root / "images" / "cam0" / "timestamps.txt").read_text().split()]
    with open_take(exported.take) as tk:
        for sensor in tk.event_sensors:
            path = root / "events" / sensor / "events.h5"
            with h5py.File(path, "r") as f:
                assert f["events/p"].dtype == np.uint8
                assert set(np.unique(f["events/p"][()]).tolist()) <= {0, 1}
                off, n = int(f["t_offset"][()]), f["events/t"].shape[0]
                t_all = f["events/t"][()].astype(np.int64)
            assert np.all(np.diff(t_all) >= 0)
            # cropped to the frames' span: first exposure start .. last exposure end
            assert off <= stamps[0]
            assert t_all[-1] + off <= stamps[-1] + 10_000
            assert n == len(tk.events(sensor, off, int(t_all[-1]) + off + 1))
            for a, b in ((stamps[3], stamps[4]), (stamps[10] + 17, stamps[20] - 5)):
                got = _slice_dsec(path, a, b)
                ref = tk.events(sensor, a, b)
                assert len(ref) > 100
                np.testing.assert_array_equal(got["t"], ref.t)
                np.testing.assert_array_equal(got["x"], ref.x)
                # 1/0 in the file, +1/-1 from Take
                np.testing.assert_array_equal(got["p"].astype(np.int8) * 2 - 1, ref.p)
            with h5py.File(root / "events" / sensor / "rectify_map.h5", "r") as f:
                assert f["rectify_map"].shape == (RES[1], RES[0], 2)


def test_voxel_grids_hold_each_frames_events(exported: Fixture) -> None:
    root = exported.out["nerfstudio"]
    with open_take(exported.take) as tk:
        for sensor in tk.event_sensors:
            with h5py.File(root / "events" / sensor / "voxels.h5", "r") as f:
                vox, win = f["voxels"], f["window_us"][()]
                assert vox.shape == (30, 5, RES[1], RES[0])
                for k in (0, 7, 29):
                    a, b = int(win[k, 0]), int(win[k, 1])
                    ev = tk.events(sensor, a + 1, b + 1)  # the window is (a, b]
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
    _store_truth(take, exported.scene, dist)
    out = tmp_path / "out"
    run_export(ExportOptions(take=take, format="nerfstudio", out=out))
    views = read_nerfstudio(out)
    pattern = (exported.scene.cols, exported.scene.rows)
    checked = []
    with open_take(take) as tk:
        K = tk.calibration["cam1"]["K"]  # type: ignore[index]
        fs = tk.frames("cam1")
        mids = fs.timestamps_us + np.array([fs[i].exposure_us // 2 for i in range(len(fs))])
        for v in (v for v in views["train"] if v.camera == "cam1"):
            assert abs(v.K[0, 2] - (RES[0] - 1) / 2) < 1e-6  # centred principal point
            i = int(np.flatnonzero(mids == v.t_us)[0])
            raw = np.asarray(fs[i].image, np.uint8)
            ok, c0 = cv2.findChessboardCorners(raw, pattern)
            exp = _detect(v.image, pattern)
            if not ok or exp is None:
                continue
            und = cv2.undistortPoints(_refine(raw, c0, pattern), K, np.array(dist), P=v.K).reshape(-1, 2)
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
