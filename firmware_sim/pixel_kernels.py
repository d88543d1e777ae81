"""The per-pixel rule of the event-camera model (`firmware_sim.event_model`), as numba kernels:
input values to log levels, the optional low-pass, the threshold crossings of a linear level
change and their interpolated times, and `step_kernel`, the serial reference step over a
whole frame that the threaded step (`firmware_sim.keyed_step`) must match to the bit."""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

F32 = NDArray[np.float32]
Frame = NDArray[np.float32] | NDArray[np.uint8]
"""A frame as the step kernels read it: uint8 as given, any other input as float32."""
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: A change counts as a crossing when it reaches the threshold within this fraction of it:
#: float32 log frames carry ~1e-7 relative error, so a ramp of exactly k*C must give k events.
CROSSING_TOLERANCE = 1e-5

# The kernels take their inputs grouped in plain tuples (numba's cache pickles a NamedTuple
# argument's class by name, so renaming one would break loading older caches):
LogInput = tuple[bool, float, float, float]
"""How input values become log levels (`_to_log`): is_log, scale to DN, eps, knee (DN)."""
Pixels = tuple[F64, F64, F64, F64, I64]
"""Per-pixel (H, W) arrays `step_kernel` reads and advances: level, ref, thr_on, thr_off, last_t."""
StepParams = tuple[float, bool, float, float, int]
"""Non-idealities `step_kernel` applies: leak rate (Hz), low-pass on, its cutoff (Hz) and minimum
fraction, refractory period (us)."""
EventOut = tuple[NDArray[np.uint16], NDArray[np.uint16], NDArray[np.int8], I64]


@njit(nogil=True, cache=True, inline="always")
def _to_log(v: float, conv: LogInput) -> tuple[float, float]:
    """(log level, linear intensity in DN) of one input value; lin-log as in firmware_sim.scene."""
    is_log, scale, eps, knee = conv
    log_knee = math.log(knee)
    if is_log:
        lv = v
        inten = math.exp(lv) - eps if lv >= log_knee else (lv - log_knee) * knee + knee - eps
        return lv, max(inten, 0.0)
    inten = max(v * scale, 0.0)
    u = inten + eps
    # Both segments for every value, then a select: a dark/bright texture would otherwise
    # mispredict the branch at every other pixel (log(max(u, knee)) is log(u) where used).
    lg = math.log(max(u, knee))
    lin = log_knee + (u - knee) / knee
    return (lg if u >= knee else lin), inten


@njit(nogil=True, cache=True)
def init_state_kernel(  # pragma: no cover - numba
    frame: F32, conv: LogInput, level: F64, ref: F64, ref_offset: F64
) -> None:
    """Set the level and the reference (level - ref_offset) of every pixel from the first frame."""
    h, w = frame.shape
    for i in range(h):
        for j in range(w):
            lv, _ = _to_log(frame[i, j], conv)
            level[i, j] = lv
            ref[i, j] = lv - ref_offset[i, j]


@njit(nogil=True, cache=True, inline="always")
def level_gain(v: float, conv: LogInput, prm: StepParams, dt_s: float) -> tuple[float, float]:
    """(log level of input value v, low-pass gain of the step: 1 - exp(-dt / tau); 1 when off)."""
    _leak, lowpass, lowpass_hz, lowpass_min, _refr = prm
    lv, inten = _to_log(v, conv)
    if lowpass:
        frac = max(inten / 255.0, lowpass_min)
        tau = 1.0 / (2.0 * math.pi * lowpass_hz * frac)
        return lv, 1.0 - math.exp(-dt_s / tau)
    return lv, 1.0


@njit(nogil=True, cache=True, inline="always")
def filtered(lp: float, lv: float, a: float, lowpass: bool) -> float:
    """Log level at the end of the step: the input's, low-passed from `lp` (gain a) if asked."""
    return lp + a * (lv - lp) if lowpass else lv


@njit(nogil=True, cache=True, inline="always")
def new_level(v: float, conv: LogInput, lp: float, prm: StepParams, dt_s: float) -> float:
    """Log level of a pixel at the end of the step from input value v and the level lp before."""
    lv, a = level_gain(v, conv, prm, dt_s)
    return filtered(lp, lv, a, prm[1])


@njit(nogil=True, cache=True)
def level_table(conv: LogInput, prm: StepParams, dt_s: float) -> F64:  # pragma: no cover - numba
    """(2, 256): `level_gain` of every uint8 value, as the kernels compute it from float32 frames."""
    table = np.empty((2, 256), np.float64)
    for v in range(256):
        lv, a = level_gain(np.float32(v), conv, prm, dt_s)  # type: ignore[arg-type]
        table[0, v] = lv
        table[1, v] = a
    return table


@njit(nogil=True, cache=True, inline="always")
def crossings(
    lp: float, ln: float, r: float, con: float, coff: float, leak_rate_hz: float, dt_s: float
) -> tuple[int, int, float, float, float, float]:
    """(k, sign, threshold, d0, slope, drift) of a pixel going lp -> ln with reference r.

    d(s) = level(s) - ref(s) runs from d0 to d0 + slope over the step (the reference
    drifts down by `drift`, the leak); k crossings of sign * m * threshold, m = 1..k.
    """
    drift = leak_rate_hz * con * dt_s
    d0 = lp - r
    d1 = ln - r + drift
    k = 0
    sign = 0
    c = con
    if d1 >= con * (1.0 - CROSSING_TOLERANCE):
        k = max(1, int(d1 / con + CROSSING_TOLERANCE))
        sign = 1
    elif d1 <= -coff * (1.0 - CROSSING_TOLERANCE):
        k = max(1, int(-d1 / coff + CROSSING_TOLERANCE))
        sign = -1
        c = coff
    return k, sign, c, d0, d1 - d0, drift


@njit(nogil=True, cache=True, inline="always")
def event_time(m: int, sign: int, c: float, d0: float, slope: float, t0: int, t1: int, dt: float) -> int:
    """Time (us, inside (t0, t1]) of the m-th crossing: linear interpolation, rounded."""
    target = sign * m * c
    s = (target - d0) / slope if slope != 0.0 else 1.0
    s = min(max(s, 0.0), 1.0)
    te = t0 + int(s * dt + 0.5)  # s * dt >= 0: truncation rounds to nearest
    return min(max(te, t0 + 1), t1)


@njit(nogil=True, cache=True)
def step_kernel(  # pragma: no cover - numba
    frame: F32, conv: LogInput, px: Pixels, prm: StepParams, t0: int, t1: int, i0: int, out: EventOut, n: int
) -> tuple[int, int]:
    """Events of every pixel for the step (t0, t1], in raster order; updates the state in place.

    The serial reference of the rule (the simulator runs the two-pass block kernels
    below, which give the same events; tests compare them). Per pixel: new level
    (low-passed if asked), d(s) = level(s) - ref(s) linear in the step fraction s (ref
    drifts down by the leak), one event per crossing of +m*C_on or -m*C_off at
    t0 + s*(t1 - t0) rounded to the us and kept inside (t0, t1]. The state of a pixel
    changes only with its events, so when the outputs are full the kernel stops before
    that pixel and returns (n, its flat index) for the caller to grow the outputs and
    resume from (as i0); (n, h*w) when done.
    """
    level, ref, thr_on, thr_off, last_t = px
    leak_rate_hz = prm[0]
    refractory_us = prm[4]
    out_x, out_y, out_p, out_t = out
    h, w = frame.shape
    dt = float(t1 - t0)
    dt_s = dt * 1e-6
    for idx in range(i0, h * w):
        i = idx // w
        j = idx - i * w
        lp = level[i, j]
        ln = new_level(frame[i, j], conv, lp, prm, dt_s)
        r = ref[i, j]
        k, sign, c, d0, slope, drift = crossings(lp, ln, r, thr_on[i, j], thr_off[i, j], leak_rate_hz, dt_s)
        if k > 0:
            if n + k > out_x.shape[0]:
                return n, idx
            lt = last_t[i, j]
            for m in range(1, k + 1):
                te = event_time(m, sign, c, d0, slope, t0, t1, dt)
                if te - lt < refractory_us:
                    continue
                out_x[n] = j
                out_y[n] = i
                out_p[n] = sign
                out_t[n] = te
                n += 1
                lt = te
            last_t[i, j] = lt
            r += sign * k * c
        level[i, j] = ln
        ref[i, j] = r - drift
    return n, h * w
