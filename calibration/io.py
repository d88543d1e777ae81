# ruff: noqa: N806  (K, R, T, J follow the notation of the calibration literature)
"""Calibration outputs: OpenCV YAML (cv2.FileStorage), Kalibr camchain YAML, JSON.

OpenCV YAML uses the names of OpenCV's own calibration sample (camera_matrix,
distortion_coefficients, image_width/height) so existing tools read it; rig files add R and T per
camera (x_cam = R x_rig + T). Kalibr's camchain has `T_cn_cnm1`, the transform from the previous
camera's frame into camera n, and only the radtan (k1 k2 p1 p2) distortion model, so richer lens
models are refused rather than silently truncated.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import yaml

from calibration.errors import CalibrationError
from calibration.extrinsics import RigResult
from calibration.intrinsics import IntrinsicsResult

log = logging.getLogger(__name__)


def write_json(result: IntrinsicsResult | RigResult, path: str | Path) -> None:
    """The full result (per-view and per-corner data included) as JSON."""
    Path(path).write_text(result.model_dump_json(indent=2))
    log.info("wrote %s", path)


def _write_camera(fs: cv2.FileStorage, prefix: str, intr: IntrinsicsResult) -> None:
    fs.write(f"{prefix}image_width", int(intr.image_size[0]))
    fs.write(f"{prefix}image_height", int(intr.image_size[1]))
    fs.write(f"{prefix}camera_matrix", intr.camera_matrix())
    fs.write(f"{prefix}distortion_coefficients", intr.dist_coeffs().reshape(1, -1))
    fs.write(f"{prefix}distortion_model", intr.model)
    fs.write(f"{prefix}avg_reprojection_error", float(intr.rms_px))


def write_opencv_yaml(
    intrinsics: IntrinsicsResult | dict[str, IntrinsicsResult], path: str | Path, rig: RigResult | None = None
) -> None:
    """One camera (keys without prefix) or a rig (keys prefixed by `<camera>_`, plus R and T)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise CalibrationError(f"{path}: cannot open for writing")
    try:
        if isinstance(intrinsics, IntrinsicsResult):
            fs.write("camera_name", intrinsics.camera)
            _write_camera(fs, "", intrinsics)
        else:
            fs.write("cameras", ",".join(intrinsics))
            for name, intr in intrinsics.items():
                _write_camera(fs, f"{name}_", intr)
                if rig is not None:
                    R, t = rig.pose(name)
                    fs.write(f"{name}_R", R)
                    fs.write(f"{name}_T", t.reshape(3, 1))
            if rig is not None:
                fs.write("rig_reference", rig.reference)
                fs.write("rig_rms_px", float(rig.rms_px))
    finally:
        fs.release()
    log.info("wrote %s", path)


def read_opencv_yaml(path: str | Path) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """(K, dist, (width, height)) of a single-camera file written by write_opencv_yaml."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise CalibrationError(f"{path}: cannot open for reading")
    try:
        K = fs.getNode("camera_matrix").mat()
        dist = fs.getNode("distortion_coefficients").mat()
        size = (int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real()))
    finally:
        fs.release()
    if K is None or dist is None:
        raise CalibrationError(f"{path}: no camera_matrix / distortion_coefficients")
    return np.asarray(K, np.float64), np.asarray(dist, np.float64).ravel(), size


def _radtan(intr: IntrinsicsResult) -> list[float]:
    d = intr.dist_coeffs()
    extra = d[4:] if d.size > 4 else np.zeros(0)
    if np.any(np.abs(extra) > 0):
        raise CalibrationError(
            f"camera {intr.camera}: lens model {intr.model} has terms beyond k1 k2 p1 p2, which Kalibr's "
            "radtan model cannot hold; calibrate with --model k1k2+tangential or write OpenCV YAML"
        )
    return [float(v) for v in d[:4]]


def kalibr_camchain(
    intrinsics: dict[str, IntrinsicsResult],
    rig: RigResult | None = None,
    topics: dict[str, str] | None = None,
) -> dict[str, object]:
    """The camchain as a dict (cam0, cam1, ... in the order of `intrinsics`), laid out as Kalibr's
    own output: `cam_overlaps` lists the indices of the cameras each one saw the board with (its
    validator's getCamOverlaps reads it; empty without a rig calibration)."""
    out: dict[str, object] = {}
    names = list(intrinsics)
    for i, name in enumerate(names):
        intr = intrinsics[name]
        K = intr.camera_matrix()
        entry: dict[str, object] = {
            "camera_model": "pinhole",
            "intrinsics": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])],
            "distortion_model": "radtan",
            "distortion_coeffs": _radtan(intr),
            "resolution": [int(intr.image_size[0]), int(intr.image_size[1])],
            "rostopic": (topics or {}).get(name, f"/{name}/image_raw"),
        }
        overlaps = rig.overlaps.get(name, []) if rig is not None else []
        entry["cam_overlaps"] = [names.index(o) for o in overlaps if o in names]
        if rig is not None and i > 0:
            Ra, ta = rig.pose(names[i - 1])
            Rb, tb = rig.pose(name)
            T = np.eye(4)
            T[:3, :3] = Rb @ Ra.T
            T[:3, 3] = tb - T[:3, :3] @ ta
            entry["T_cn_cnm1"] = T.tolist()
        out[f"cam{i}"] = entry
    return out


def write_kalibr_camchain(
    intrinsics: dict[str, IntrinsicsResult], path: str | Path, rig: RigResult | None = None
) -> None:
    Path(path).write_text(yaml.safe_dump(kalibr_camchain(intrinsics, rig), sort_keys=False))
    log.info("wrote %s", path)


def write_result(result: IntrinsicsResult, path: str | Path) -> None:
    """By extension: .json -> JSON, .yaml/.yml/.xml -> OpenCV FileStorage."""
    suffix = Path(path).suffix.lower()
    if suffix == ".json":
        write_json(result, path)
    elif suffix in (".yaml", ".yml", ".xml"):
        write_opencv_yaml(result, path)
    else:
        raise CalibrationError(f"{path}: unknown output format {suffix!r} (use .yaml, .yml, .xml or .json)")


def dumps_summary(result: IntrinsicsResult | RigResult) -> str:
    """What `--json` prints: the result without per-corner data."""
    data = result.summary() if isinstance(result, IntrinsicsResult) else result.model_dump()
    return json.dumps(data, indent=2)
