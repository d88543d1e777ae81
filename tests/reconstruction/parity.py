"""Comparing a float32 voxel grid with the float64 numpy reference (`voxel_grid_bincount`).

Unnormalised grids must agree to float32 rounding. Normalisation standardises the non-zero
entries; an entry where polarities cancel is an exact zero in one precision and a rounding
residue (~1e-8) in the other, so the two may standardise slightly different sets of entries.
Where the sets agree the normalised grids must agree to float32 rounding; where they do not,
the disagreeing entries must be residues, and the grid must be the reference's standardisation
applied to its own unnormalised values.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

RTOL = ATOL = 1e-5
#: Largest rounding residue a cancelled entry leaves in the test cases (a few dozen events).
RESIDUE = 1e-5


def standardize_reference(raw: NDArray[np.float32]) -> NDArray[np.float32]:
    """The reference's normalisation (`voxel_grid_bincount`) applied to a given grid."""
    grid = raw.astype(np.float64)
    nz = grid != 0
    if not nz.any():
        return grid.astype(np.float32)
    mean, std = grid[nz].mean(), grid[nz].std()
    return np.where(nz, (grid - mean) / (std if std > 0 else 1.0), 0.0).astype(np.float32)


def assert_voxel_parity(
    raw: NDArray[np.float32],
    ref_raw: NDArray[np.float32],
    norm: NDArray[np.float32] | None = None,
    ref_norm: NDArray[np.float32] | None = None,
) -> None:
    """`raw` (and `norm`) against the reference's grids of the same window."""
    assert raw.dtype == np.float32
    assert raw.shape == ref_raw.shape
    np.testing.assert_allclose(raw, ref_raw, rtol=RTOL, atol=ATOL)
    if norm is None or ref_norm is None:
        return
    agree = (raw != 0) == (ref_raw != 0)
    if agree.all():
        np.testing.assert_allclose(norm, ref_norm, rtol=RTOL, atol=ATOL)
        return
    assert np.abs(raw[~agree]).max() < RESIDUE
    assert np.abs(ref_raw[~agree]).max() < RESIDUE
    np.testing.assert_allclose(norm, standardize_reference(raw), rtol=RTOL, atol=ATOL)
