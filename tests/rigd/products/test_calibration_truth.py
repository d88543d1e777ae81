# ruff: noqa: N806  (K, R, t follow the notation of the calibration literature)
"""A calibration's error against a simulated take's ground truth, in the calibration's rig frame."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from rigd.products.calibration_truth import intrinsics_error, rig_errors


def _pose(rvec: list[float], t: list[float]) -> tuple[np.ndarray, np.ndarray]:
    return cv2.Rodrigues(np.array(rvec, np.float64))[0], np.array(t, np.float64)


def test_errors_are_measured_in_the_calibrations_reference_frame() -> None:
    K = np.array([[500.0, 0, 240], [0, 500, 135], [0, 0, 1]])
    R0, t0 = _pose([0.0, 0.3, 0.0], [0.1, 0.0, 3.0])  # truth: cam0 is not at the origin
    R1, t1 = _pose([0.0, -0.1, 0.02], [-0.5, 0.01, 2.9])
    truth = {
        "cam0": {"intrinsics": {"K": K.tolist()}, "pose": {"R": R0.tolist(), "t": t0.tolist()}},
        "cam1": {"intrinsics": {"K": K.tolist()}, "pose": {"R": R1.tolist(), "t": t1.tolist()}},
    }
    # The calibration's rig frame is cam1's: exact poses relative to it score zero.
    R01 = R0 @ R1.T
    exact = {"cam1": (np.eye(3), np.zeros(3)), "cam0": (R01, t0 - R01 @ t1)}
    errs = {e.device: e for e in rig_errors(truth, {"cam0": K, "cam1": K}, exact, "cam1")}
    assert errs["cam0"].centre_mm == pytest.approx(0.0, abs=1e-9)
    assert errs["cam0"].rotation_deg == pytest.approx(0.0, abs=1e-6)
    # cam0's centre moved 2 mm along x of the rig, turned 0.5 degrees, focal 1.5 px off.
    R_off = cv2.Rodrigues(np.array([0.0, np.radians(0.5), 0.0]))[0]
    Rb = R_off @ R01
    C = -R01.T @ (t0 - R01 @ t1) + np.array([0.002, 0, 0])
    K2 = K.copy()
    K2[0, 0] += 1.5
    K2[0, 2] += 0.3
    off = {"cam1": (np.eye(3), np.zeros(3)), "cam0": (Rb, -Rb @ C)}
    e = {x.device: x for x in rig_errors(truth, {"cam0": K2, "cam1": K}, off, "cam1")}["cam0"]
    assert e.centre_mm == pytest.approx(2.0, abs=1e-6)
    assert e.rotation_deg == pytest.approx(0.5, abs=1e-6)
    assert e.focal_px == pytest.approx(1.5)
    assert e.principal_px == pytest.approx(0.3)
    assert "cam0 vs simulator ground truth: focal 1.500 px" in e.line()


def test_intrinsics_error_of_an_event_sensor() -> None:
    K = np.array([[250.0, 0, 160], [0, 250, 90], [0, 0, 1]])
    K2 = K + np.array([[0, 0, 3.0], [0, -2.0, 4.0], [0, 0, 0]])
    e = intrinsics_error("ev0", {"intrinsics": {"K": K.tolist()}}, K2)
    assert (e.focal_px, e.principal_px) == (2.0, 5.0)
    assert e.centre_mm is None
