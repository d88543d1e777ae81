# ruff: noqa: N806  (R, t follow the notation of the calibration literature)
"""A joined simulated take's ground-truth calibration, in one rig frame.

A simulated take stores each device's exact pose in the frame of its first device (cameras
first, rigd/app/capture/truth.py). Each part of a multi-host take did so for its own devices,
so a follower's poses are in the frame of that host's first device. The joined take re-expresses
every ground-truth pose in the frame of the whole rig's first device, from the truth each
device's `info_json` carries, exactly as a one-host capture of the rig stores it. A calibration
`rigd calibrate` stored (not the simulator's truth) is left as it is.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

import h5py
import numpy as np
from pydantic import ValidationError

from rigd.core.devices import DeviceInfo, GroundTruth
from rigd.take.calibration import GROUND_TRUTH_SOURCE, write_board_pose, write_calibration_group
from rigd.take.h5file import attr_text

log = logging.getLogger(__name__)


def device_info(g: h5py.Group) -> DeviceInfo | None:
    """The DeviceInfo a device group stores (None when it stores none that parses)."""
    raw = g.attrs.get("info_json")
    if raw is None:
        return None
    try:
        return DeviceInfo.model_validate_json(attr_text(raw))
    except ValidationError as exc:
        log.warning("%s: info_json does not parse (%s); its ground truth is not rebased", g.name, exc)
        return None


def _source(g: h5py.Group) -> str | None:
    import json

    node = g.get("result_json")
    if not isinstance(node, h5py.Dataset):
        return None
    try:
        data = json.loads(attr_text(node[()]))
    except (ValueError, TypeError) as exc:
        log.warning("%s: result_json is not JSON (%s); left as it is", node.name, exc)
        return None
    return data.get("source") if isinstance(data, dict) else None


def rebase_ground_truth(f: h5py.File, infos: Mapping[str, DeviceInfo | None]) -> list[str]:
    """Rewrite the ground-truth calibrations of `f` in the frame of the first device of `infos`
    (ordered as the rig: cameras first); returns the devices rewritten. Nothing is rewritten
    unless every device carries truth of one world (as at capture)."""
    truths = {n: (GroundTruth.of(i) if i is not None else None) for n, i in infos.items()}
    known = {n: g for n, g in truths.items() if g is not None}
    calib = f.get("calibration")
    if not known or len(known) != len(truths) or len({g.world for g in known.values()}) != 1:
        return []
    if not isinstance(calib, h5py.Group):
        return []
    ref = next(iter(known.values()))
    R0, t0 = np.asarray(ref.R, np.float64), np.asarray(ref.t, np.float64)
    done = []
    for name, g in known.items():
        node = calib.get(name)
        if not isinstance(node, h5py.Group) or _source(node) != GROUND_TRUTH_SOURCE:
            continue
        R, t = np.asarray(g.R, np.float64), np.asarray(g.t, np.float64)
        R_rig = R @ R0.T
        intrinsics = {"K": g.K, "dist": g.dist, "image_size": list(g.image_size)}
        pose = {"R": R_rig.tolist(), "t": (t - R_rig @ t0).tolist()}
        write_calibration_group(f, name, intrinsics, pose, GROUND_TRUTH_SOURCE)
        done.append(name)
    if done and attr_text(calib.attrs.get("board_source", "")) in ("", GROUND_TRUTH_SOURCE):
        write_board_pose(f, R0, t0, GROUND_TRUTH_SOURCE)
    log.debug("rebased the ground truth of %s on %s", done, next(iter(known)))
    return done
