"""The rig timebase: int64 microseconds of the trigger box clock.

Every device clock maps to it by an offset and a drift fitted on the trigger pulses the
device saw. Arithmetic keeps the int64 difference exact and only the rate product in
float64, so hours-long takes keep sub-microsecond precision.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rigd.core.errors import SyncError

#: Events are mapped in blocks of this many to bound temporary memory.
_BLOCK = 1 << 20


def pulse_offset_us(k: int, rate_hz: float) -> int:
    """Box time of pulse k after pulse 0: round(k * 1e6 / rate), the exact rational with halves
    rounded up (docs/trigger-protocol.md, "Pulses"). A protocol rate has at most six decimals,
    so rate * 1e6 is an exact integer and this is integer arithmetic, as in the firmware."""
    rate_uhz = round(rate_hz * 1e6)
    return (2 * k * 10**12 + rate_uhz) // (2 * rate_uhz)


@dataclass(frozen=True, slots=True)
class ClockMap:
    """rig_us = rig_ref_us + frac_us + rate * (device_us - device_ref_us).

    The references are integers so the subtraction is exact; `frac_us` (|frac| <= 0.5)
    keeps the sub-microsecond part of the fitted offset.
    """

    device_ref_us: int
    rig_ref_us: int
    rate: float = 1.0
    frac_us: float = 0.0

    @classmethod
    def identity(cls) -> ClockMap:
        return cls(0, 0, 1.0, 0.0)

    @property
    def drift_ppm(self) -> float:
        """How fast the device clock runs against the rig clock, in ppm (positive: device fast)."""
        return (1.0 / self.rate - 1.0) * 1e6

    def to_rig(self, device_us: ArrayLike) -> NDArray[np.int64]:
        t = np.asarray(device_us, dtype=np.int64)
        out = np.empty(t.shape, np.int64)
        flat_in, flat_out = t.reshape(-1), out.reshape(-1)
        for i in range(0, flat_in.size, _BLOCK):
            d = (flat_in[i : i + _BLOCK] - self.device_ref_us).astype(np.float64)
            flat_out[i : i + _BLOCK] = (
                np.rint(d * self.rate + self.frac_us).astype(np.int64) + self.rig_ref_us
            )
        return out

    def to_device(self, rig_us: ArrayLike) -> NDArray[np.int64]:
        r = np.asarray(rig_us, dtype=np.int64)
        d = ((r - self.rig_ref_us).astype(np.float64) - self.frac_us) / self.rate
        return np.rint(d).astype(np.int64) + self.device_ref_us

    def to_rig_float(self, device_us: ArrayLike) -> NDArray[np.float64]:
        """Unrounded rig time, for residuals and tests."""
        t = np.asarray(device_us, dtype=np.int64)
        return (t - self.device_ref_us).astype(np.float64) * self.rate + self.frac_us + float(self.rig_ref_us)


@dataclass(frozen=True, slots=True)
class ClockFit:
    """A fitted clock map and how well the pulses agree with it."""

    map: ClockMap
    residuals_us: NDArray[np.float64]

    @property
    def n(self) -> int:
        return int(self.residuals_us.size)

    @property
    def rms_us(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_us**2))) if self.n else float("nan")

    @property
    def max_abs_us(self) -> float:
        return float(np.max(np.abs(self.residuals_us))) if self.n else float("nan")


def fit_clock_map(device_us: ArrayLike, rig_us: ArrayLike, *, fit_drift: bool = True) -> ClockFit:
    """Least-squares offset (+ drift) from matched pulse times in both clocks.

    With one pulse, or `fit_drift=False`, only the offset is fitted (rate 1).
    """
    d = np.asarray(device_us, dtype=np.int64)
    r = np.asarray(rig_us, dtype=np.int64)
    if d.shape != r.shape or d.ndim != 1:
        raise SyncError(f"need two 1-D arrays of equal length, got {d.shape} and {r.shape}")
    if d.size == 0:
        raise SyncError("cannot fit a clock map on zero matched pulses")
    d_ref, r_ref = int(d[0]), int(r[0])
    x = (d - d_ref).astype(np.float64)
    y = (r - r_ref).astype(np.float64)
    if fit_drift and d.size >= 2 and np.ptp(x) > 0:
        xm, ym = x.mean(), y.mean()
        rate = float(np.dot(x - xm, y - ym) / np.dot(x - xm, x - xm))
        intercept = ym - rate * xm
    else:
        rate = 1.0
        intercept = float(np.mean(y - x))
    if not np.isfinite(rate) or rate <= 0:
        raise SyncError(f"fitted clock rate {rate!r} is not a positive finite number")
    shift = int(np.rint(intercept))
    cmap = ClockMap(d_ref, r_ref + shift, rate, float(intercept - shift))
    exact = x * rate + intercept
    residuals = exact - y
    return ClockFit(cmap, residuals)
