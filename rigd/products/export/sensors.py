# ruff: noqa: N803, N806  (K, R, t follow the notation of the calibration literature)
"""Event-sensor products every format carries: calibration, undistortion maps, per-frame
voxel grids as supervision, and the reconstruction's segments/keyframes when given.

Layout under the export directory (docs/export.md):
    events/<sensor>/calibration.json   K, dist, image_size, R, t (rig frame), K_rect, t0_us
    events/<sensor>/undistort_map.npz  map_x, map_y (undistorted pixel -> raw pixel, cv2.remap),
                                       rectify_map (raw pixel -> undistorted pixel, DSEC's)
    events/<sensor>/voxels.h5          voxels (T, bins, H, W) float32 in raw sensor pixels, Zstd
                                       (`import hdf5plugin` before h5py reads it);
                                       window_us (T, 2) = (previous timestep, this timestep]
    segments/<sensor>.json             segments.json of `rigd reconstruct` + export times
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import cv2
import hdf5plugin
import numpy as np
from numpy.typing import NDArray

from reconstruction.representations import voxel_grid
from rigd.core.errors import ConfigError
from rigd.core.progress import ProgressUpdate
from rigd.products.export.common import ExportPlan, pinhole_for
from rigd.products.export.outputs import h5_output

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


def rectify_map(K: F64, dist: F64, K_new: F64, size: tuple[int, int]) -> NDArray[np.float32]:
    """(H, W, 2): undistorted pixel coordinates of every raw pixel centre (DSEC's rectify_map)."""
    w, h = size
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1)[:, None, :]
    und = cv2.undistortPoints(pts, K, dist, P=K_new)
    return und.reshape(h, w, 2).astype(np.float32)


def sensor_calibration(plan: ExportPlan, sensor: str) -> dict[str, Any] | None:
    """The sensor's stored calibration with its rectified pinhole K, or None if uncalibrated."""
    c = (plan.take.calibration or {}).get(sensor)
    if c is None or "K" not in c:
        return None
    size = (int(c["image_size"][0]), int(c["image_size"][1]))
    K = np.asarray(c["K"], np.float64)
    dist = np.asarray(c["dist"], np.float64).ravel()
    K_rect, _ = pinhole_for(K, dist, size, None)
    out: dict[str, Any] = {
        "K": K.tolist(),
        "dist": dist.tolist(),
        "image_size": list(size),
        "K_rect": K_rect.tolist(),
        "convention": "x_cam = R x_world + t (OpenCV axes, metres, pixel centres at integers); world: "
        + plan.world_note,
    }
    if "R" in c and "t" in c:
        R, t = plan.world_pose(np.asarray(c["R"], np.float64), np.asarray(c["t"], np.float64).ravel())
        out["R"], out["t"] = R.tolist(), t.tolist()
    return out


def write_sensor_maps(plan: ExportPlan, sensor: str, dest: Path) -> dict[str, Any] | None:
    """calibration.json and undistort_map.npz of one sensor; None (and a warning) if uncalibrated."""
    calib = sensor_calibration(plan, sensor)
    if calib is None:
        log.warning("%s: %s has no stored calibration; exported without maps", plan.take.path, sensor)
        return None
    dest.mkdir(parents=True, exist_ok=True)
    K, dist, K_rect = (np.asarray(calib[k], np.float64) for k in ("K", "dist", "K_rect"))
    size = (int(calib["image_size"][0]), int(calib["image_size"][1]))
    map_x, map_y = cv2.initUndistortRectifyMap(K, dist, None, K_rect, size, cv2.CV_32FC1)
    np.savez_compressed(
        dest / "undistort_map.npz", map_x=map_x, map_y=map_y, rectify_map=rectify_map(K, dist, K_rect, size)
    )
    (dest / "calibration.json").write_text(json.dumps(calib, indent=2))
    return calib


def voxel_windows(times_us: NDArray[np.int64]) -> NDArray[np.int64]:
    """(T, 2) windows (t_{k-1}, t_k] ending at each timestep; the first spans one step back."""
    t = np.asarray(times_us, np.int64)
    step = int(t[1] - t[0]) if t.size > 1 else 33_333
    start = np.concatenate([[t[0] - step], t[:-1]])
    return np.stack([start, t], axis=1)


def write_voxels(plan: ExportPlan, sensor: str, dest: Path) -> int:
    """voxels.h5 of one sensor: one (bins, H, W) grid per exported timestep; returns T."""
    w, h = plan.take.sensor(sensor).geometry
    bins = plan.options.voxel_bins
    times = plan.frames.step_times_us
    win = voxel_windows(times)
    dest.mkdir(parents=True, exist_ok=True)
    with h5_output(dest / "voxels.h5") as out:
        f = out.file
        ds = f.create_dataset(
            "voxels",
            (len(times), bins, h, w),
            np.float32,
            chunks=(1, bins, h, w),
            **hdf5plugin.Zstd(clevel=1),
        )
        for k, (a, b) in enumerate(win):
            # (a, b]: events at a belong to the previous window, events at b to this one.
            ev = plan.take.sensor(sensor).events(int(a) + 1, int(b) + 1)
            ds[k] = voxel_grid(ev, w, h, bins, int(a), int(b))
            out.check()
            if (k + 1) % 10 == 0 or k + 1 == len(times):
                plan.progress(
                    ProgressUpdate(f"voxels {sensor}", f"{k + 1}/{len(times)} grids", k + 1, len(times))
                )
        f.create_dataset("window_us", data=win)
        f.create_dataset("frame_time_us", data=times)
        f.create_dataset("train", data=plan.frames.train)
        f.attrs["bins"] = bins
        f.attrs["polarity"] = "voxel values sum +1 (ON) / -1 (OFF) with bilinear weights in time"
        f.attrs["pixels"] = "raw sensor pixels; undistort with undistort_map.npz (map_x, map_y)"
    return len(times)


def _read_segments(src: Path) -> dict[str, Any]:
    """A segments.json with an integer keyframe_us (rig us) in every segment; a ConfigError names
    the file and the first bad entry (NaN, a float, a missing key, not JSON)."""
    try:
        data = json.loads(src.read_text())
        segments = data.get("segments", []) if isinstance(data, dict) else None
        if not isinstance(segments, list):
            raise ValueError("no list of segments")
        for i, s in enumerate(segments):
            key = s.get("keyframe_us") if isinstance(s, dict) else None
            if not isinstance(key, int) or isinstance(key, bool) or abs(key) >= 2**63:
                raise ValueError(f"segment {i}: keyframe_us {key!r} is not an int64 of rig us")
    except (OSError, ValueError) as exc:
        raise ConfigError(f"--segments {src}: {exc}") from exc
    data["segments"] = segments
    return dict(data)


def write_segments(plan: ExportPlan) -> list[Path]:
    """Copy `rigd reconstruct`'s segments.json of this take (one per sensor), adding each
    keyframe's export time in [0, 1] and its nearest exported timestep."""
    root = plan.options.segments
    if root is None:
        return []
    if not root.is_dir():
        raise ConfigError(f"--segments {root}: no such directory (a `rigd reconstruct --out` directory)")
    found = sorted((root / plan.take.take_id).glob("**/segments.json"))
    if not found:
        raise ConfigError(f"--segments {root}: no {plan.take.take_id}/<sensor>/segments.json in it")
    fr = plan.frames
    times = fr.step_times_us
    written = []
    for src in found:
        data = _read_segments(src)
        for s in data["segments"]:
            key = s["keyframe_us"]
            s["keyframe_time"] = (key - fr.t0_us) / max(fr.t1_us - fr.t0_us, 1)
            s["keyframe_step"] = int(np.argmin(np.abs(times - key)))
        name = src.parent.name if src.parent != root / plan.take.take_id else "segments"
        dest = plan.out / "segments" / f"{name}.json"
        dest.parent.mkdir(parents=True, exist_ok=True)
        dest.write_text(json.dumps(data, indent=2))
        written.append(dest)
    return written


def write_event_products(plan: ExportPlan) -> dict[str, dict[str, Any] | None]:
    """Maps and voxel grids of every event sensor, and the segments; {sensor: calibration}."""
    out: dict[str, dict[str, Any] | None] = {}
    for sensor in plan.take.event_sensors:
        dest = plan.out / "events" / sensor
        out[sensor] = write_sensor_maps(plan, sensor, dest)
        write_voxels(plan, sensor, dest)
    write_segments(plan)
    return out
