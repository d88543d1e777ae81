"""COLMAP's image poses: (w, x, y, z) quaternions with w >= 0, exact for every rotation."""

# ruff: noqa: N803  (R follows the notation of the calibration literature)

from __future__ import annotations

import numpy as np
import pytest

from rigd.products.export.colmap import rotmat_to_qvec


def qvec_to_rotmat(q: np.ndarray) -> np.ndarray:
    """COLMAP's own formula (scripts/python/read_write_model.py, qvec2rotmat)."""
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * y * y - 2 * z * z, 2 * x * y - 2 * w * z, 2 * z * x + 2 * w * y],
            [2 * x * y + 2 * w * z, 1 - 2 * x * x - 2 * z * z, 2 * y * z - 2 * w * x],
            [2 * z * x - 2 * w * y, 2 * y * z + 2 * w * x, 1 - 2 * x * x - 2 * y * y],
        ]
    )


def _rot(axis: list[float], angle: float) -> np.ndarray:
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


@pytest.mark.parametrize(
    "R",
    [
        np.eye(3),
        _rot([1, 0, 0], np.pi),  # trace -1: the branch where w is 0
        _rot([0, 1, 1], np.pi),
        _rot([1, 2, 3], 3.0),
        _rot([0, 0, 1], -0.4),
        *(
            _rot(list(np.random.default_rng(s).normal(size=3)), np.random.default_rng(s).uniform(-3.1, 3.1))
            for s in range(20)
        ),
    ],
)
def test_quaternion_rebuilds_the_rotation_with_w_not_negative(R: np.ndarray) -> None:
    q = rotmat_to_qvec(R)
    assert q[0] >= 0
    assert np.linalg.norm(q) == pytest.approx(1.0)
    np.testing.assert_allclose(qvec_to_rotmat(q), R, atol=1e-12)
