# ruff: noqa: N806  (R, t follow the notation of the calibration literature)
"""A simulated take's ground-truth calibration, stored in the take when it is created.

Why: a simulator knows every camera and event sensor exactly, so its takes export and train
without a calibration session, and a calibration run on them can be scored against the truth.
Devices report it through `DeviceInfo.facts` (`GroundTruth`), never through the simulator's own
modules. The poses are stored in the rig frame that `rigd calibrate rig` uses (the first camera's
frame), with the world's board plane as the board pose (`rigd export --world board`).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

import numpy as np

from rigd.core.devices import DeviceInfo, GroundTruth
from rigd.take.calibration import GROUND_TRUTH_SOURCE
from rigd.take.writer import TakeWriter

log = logging.getLogger(__name__)


def store_ground_truth(take: TakeWriter, infos: Mapping[str, DeviceInfo]) -> list[str]:
    """Store the truth of every device that carries one (the rig frame is the first device's,
    cameras first); returns the devices stored. Nothing is stored unless every device has it
    and all are in one world: a pose relative to a device without truth means nothing."""
    truths = {name: GroundTruth.of(info) for name, info in infos.items()}
    known = {n: g for n, g in truths.items() if g is not None}
    if not known:
        return []
    worlds = {g.world for g in known.values()}
    if len(known) != len(truths) or len(worlds) != 1:
        log.warning(
            "take %s: ground truth from %s of %s in worlds %s; none stored (every device of one world "
            "must have it)",
            take.path,
            sorted(known),
            sorted(truths),
            sorted(worlds),
        )
        return []
    ref = next(iter(known.values()))
    R0, t0 = np.asarray(ref.R, np.float64), np.asarray(ref.t, np.float64)
    for i, (name, g) in enumerate(known.items()):
        R, t = np.asarray(g.R, np.float64), np.asarray(g.t, np.float64)
        R_rig = R @ R0.T
        intrinsics = {"K": g.K, "dist": g.dist, "image_size": list(g.image_size)}
        pose = {"R": R_rig.tolist(), "t": (t - R_rig @ t0).tolist()}
        take.add_calibration(name, intrinsics, pose, GROUND_TRUTH_SOURCE, board=(R0, t0) if i == 0 else None)
    log.info("take %s: stored the simulator's ground-truth calibration of %s", take.path, sorted(known))
    return list(known)
