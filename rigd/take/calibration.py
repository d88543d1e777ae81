"""Calibration results stored in a take, next to the data they describe.

`/calibration/<device>` holds what a training job needs without parsing anything (`K`,
`dist`, `image_size`, and for a rig `R`, `t` of the device in the rig frame) plus the full
result as JSON (`result_json`: model, RMS, per-view errors, uncertainties, warnings). Writing
again replaces the device's group; the rest of the take is not touched.

A simulated take is written with its ground truth (`source` = `GROUND_TRUTH_SOURCE`) by the
capture itself, plus the pose of the scene's board plane in the rig frame (`/calibration` attrs
`board_R`, `board_t`): the plane z = 0 with x right and y down, the gravity-aligned world that
`rigd export --world board` uses.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from rigd.core.errors import TakeError, TakeFormatError
from rigd.core.layout import CALIBRATION_GROUP
from rigd.take.h5file import open_checked
from rigd.take.units import label_tree

log = logging.getLogger(__name__)


#: `source` of a calibration the simulator knew exactly (stored at capture).
GROUND_TRUTH_SOURCE = "simulator ground truth"


def write_calibration_group(
    f: h5py.File,
    device: str,
    intrinsics: dict[str, Any] | None,
    pose: dict[str, Any] | None,
    source: str,
) -> None:
    """`/calibration/<device>` in an open take (replacing an earlier one). A simulator's ground
    truth that is replaced is kept in the new payload (`ground_truth`): a calibration stored
    into a sim take can still be scored against it."""
    root = f.require_group(CALIBRATION_GROUP)
    truth = None
    if device in root:
        truth = _truth_of(_payload(root[device]))
        del root[device]
    g = root.create_group(device)
    if intrinsics is not None:
        g.create_dataset("K", data=np.asarray(intrinsics["K"], np.float64))
        g.create_dataset("dist", data=np.asarray(intrinsics["dist"], np.float64))
        g.create_dataset("image_size", data=np.asarray(intrinsics["image_size"], np.int64))
    if pose is not None:
        g.create_dataset("R", data=np.asarray(pose["R"], np.float64))
        g.create_dataset("t", data=np.asarray(pose["t"], np.float64))
    payload: dict[str, Any] = {"intrinsics": intrinsics, "pose": pose, "source": source}
    if truth is not None and source != GROUND_TRUTH_SOURCE:
        payload["ground_truth"] = truth
    g.create_dataset(
        "result_json", data=json.dumps(payload, default=_jsonable), dtype=h5py.string_dtype("utf-8")
    )


def _jsonable(v: object) -> object:
    if isinstance(v, np.ndarray | np.generic):
        return v.tolist()
    raise TypeError(f"{type(v).__name__} is not JSON serializable")


def _payload(g: h5py.Group) -> dict[str, Any]:
    raw = g["result_json"][()]
    data = json.loads(raw.decode() if isinstance(raw, bytes) else raw)
    return data if isinstance(data, dict) else {}


def _truth_of(payload: dict[str, Any]) -> dict[str, Any] | None:
    """{"intrinsics", "pose"} of the ground truth a stored payload is or carries, else None."""
    if payload.get("source") == GROUND_TRUTH_SOURCE:
        return {"intrinsics": payload.get("intrinsics"), "pose": payload.get("pose")}
    truth = payload.get("ground_truth")
    return truth if isinstance(truth, dict) else None


def read_ground_truth(f: h5py.File) -> dict[str, dict[str, Any]]:
    """{device: {"intrinsics": {K, dist, image_size}, "pose": {R, t} (rig frame of cam0)}} of a
    simulated take, whether the truth is what is stored or what a calibration replaced."""
    root = f.get(CALIBRATION_GROUP)
    out: dict[str, dict[str, Any]] = {}
    if root is None:
        return out
    for device, g in root.items():
        truth = _truth_of(_payload(g))
        if truth is not None:
            out[device] = truth
    return out


def write_board_pose(f: h5py.File, R: Any, t: Any, source: str) -> None:  # noqa: N803
    """The board plane's pose in the rig frame (x_rig = R x_board + t) as `/calibration` attrs."""
    root = f.require_group(CALIBRATION_GROUP)
    root.attrs["board_R"] = np.asarray(R, np.float64).reshape(3, 3)
    root.attrs["board_t"] = np.asarray(t, np.float64).reshape(3)
    root.attrs["board_source"] = source


def read_board_pose(f: h5py.File) -> tuple[np.ndarray, np.ndarray] | None:
    """(R, t) of the board plane in the rig frame (x_rig = R x_board + t), or None if not stored."""
    root = f.get(CALIBRATION_GROUP)
    if root is None or "board_R" not in root.attrs:
        return None
    return np.asarray(root.attrs["board_R"], np.float64), np.asarray(root.attrs["board_t"], np.float64)


def store_calibration(
    take_path: str | Path,
    device: str,
    intrinsics: dict[str, Any] | None = None,
    pose: dict[str, Any] | None = None,
    *,
    source: str = "",
) -> None:
    """Write one device's calibration (intrinsics summary and/or rig pose) into a take."""
    path = Path(take_path)
    if intrinsics is None and pose is None:
        raise TakeError(f"{path}: nothing to store for {device!r}")
    try:
        f = open_checked(path, "r+")
    except (OSError, TakeFormatError) as exc:
        raise TakeError(f"cannot open take {path} to store calibration: {exc}") from exc
    with f:
        known = set(f.get("frames", {})) | set(f.get("events", {}))
        if device not in known:
            raise TakeError(f"{path}: no camera or event sensor {device!r} (it has {sorted(known)})")
        write_calibration_group(f, device, intrinsics, pose, source)
        label_tree(f[f"{CALIBRATION_GROUP}/{device}"])
    log.info("stored calibration of %s in %s", device, path)


def read_calibration(f: h5py.File) -> dict[str, dict[str, Any]] | None:
    """{device: {"K", "dist", "image_size", "R", "t" (numpy, when present), "result": dict}}."""
    root = f.get(CALIBRATION_GROUP)
    if root is None:
        return None
    out: dict[str, dict[str, Any]] = {}
    for device, g in root.items():
        entry: dict[str, Any] = {k: g[k][()] for k in ("K", "dist", "image_size", "R", "t") if k in g}
        raw = g["result_json"][()]
        entry["result"] = json.loads(raw.decode() if isinstance(raw, bytes) else raw)
        out[device] = entry
    return out
