# ruff: noqa: N803, N806  (K, R, t follow the notation of the calibration literature)
"""A calibration scored against the ground truth a simulated take carries.

Why: a sim take knows its cameras exactly (stored at capture, `rigd.take.calibration`), so
`rigd calibrate` on it can say how far its result is from the truth, not only its RMS.
Poses are compared in the calibration's own rig frame: the truth is re-expressed relative to the
calibration's reference device, so the reference's pose error is zero by construction.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rigd.core.errors import TakeError
from rigd.take.calibration import read_ground_truth
from rigd.take.h5file import open_checked

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class TruthError:
    """One device's calibration against the truth."""

    device: str
    focal_px: float
    """Worse of |fx - fx_true|, |fy - fy_true|."""
    principal_px: float
    """Distance of the principal point from the true one."""
    centre_mm: float | None = None
    """Distance of the camera centre in the rig from the true one (rig calibrations)."""
    rotation_deg: float | None = None
    """Angle of R_true^T R (rig calibrations)."""

    def line(self) -> str:
        text = (
            f"{self.device} vs simulator ground truth: focal {self.focal_px:.3f} px, "
            f"principal point {self.principal_px:.3f} px"
        )
        if self.centre_mm is not None and self.rotation_deg is not None:
            text += f", centre {self.centre_mm:.2f} mm, rotation {self.rotation_deg:.3f} deg"
        return text


def ground_truth_of(take: Path) -> dict[str, dict[str, Any]]:
    """The truth a take carries ({} for a real rig's take)."""
    try:
        with open_checked(take, "r") as f:
            return read_ground_truth(f)
    except OSError as exc:
        raise TakeError(f"cannot open take {take} to read its ground truth: {exc}") from exc


def intrinsics_error(device: str, truth: Mapping[str, Any], K: Any) -> TruthError:
    K, K_true = np.asarray(K, np.float64), np.asarray(truth["intrinsics"]["K"], np.float64)
    focal = float(np.max(np.abs(np.diag(K)[:2] - np.diag(K_true)[:2])))
    principal = float(np.linalg.norm(K[:2, 2] - K_true[:2, 2]))
    return TruthError(device, focal, principal)


def _rel(R: F64, t: F64, R_ref: F64, t_ref: F64) -> tuple[F64, F64]:
    """A pose relative to the reference device's frame."""
    R_rel = R @ R_ref.T
    return R_rel, t - R_rel @ t_ref


def rig_errors(
    truth: Mapping[str, Mapping[str, Any]],
    K: Mapping[str, Any],
    poses: Mapping[str, tuple[Any, Any]],
    reference: str,
) -> list[TruthError]:
    """Intrinsics and pose errors of every calibrated device that has a truth."""
    ref = truth.get(reference, {}).get("pose")
    out = []
    for dev, (R, t) in poses.items():
        if dev not in truth:
            continue
        e = intrinsics_error(dev, truth[dev], K[dev])
        pose = truth[dev].get("pose")
        if ref is None or pose is None:
            out.append(e)
            continue
        R_true, t_true = _rel(
            np.asarray(pose["R"], np.float64),
            np.asarray(pose["t"], np.float64),
            np.asarray(ref["R"], np.float64),
            np.asarray(ref["t"], np.float64),
        )
        R, t = np.asarray(R, np.float64), np.asarray(t, np.float64).ravel()
        centre = float(np.linalg.norm(-R.T @ t + R_true.T @ t_true)) * 1000.0
        cos = np.clip((np.trace(R_true.T @ R) - 1.0) / 2.0, -1.0, 1.0)
        out.append(TruthError(dev, e.focal_px, e.principal_px, centre, float(np.degrees(np.arccos(cos)))))
    return out
