"""The event-camera pixel model: frames (linear or log intensity) in, change events out.

Each pixel keeps a reference log level (the level at its last event). Between two input
frames at t_prev and t the pixel's (optionally low-passed) log level is taken to move
linearly, and every crossing of reference + m * C_on (ON) or reference - m * C_off (OFF)
gives one event at the interpolated time of that crossing. Events of the step
(t_prev, t] are therefore timestamped *inside* it (no one-frame shift as in v2e), several
per pixel when the change spans several thresholds. See docs/event-simulator.md.

Non-idealities, each off unless configured (the scene decides what it needs):

* threshold mismatch: per-pixel C_on, C_off ~ N(C, sigma), drawn once from the seed;
* refractory period: a crossing less than `refractory_us` after the pixel's last event
  is not emitted, but the reference still advances (the pixel is held in reset);
* photoreceptor low-pass: first-order filter on the log level whose cutoff grows with
  the intensity (dark pixels are slow), as in v2e;
* leak: the reference drifts down by `leak_rate_hz * C_on` per second, so a static pixel
  emits ON events at `leak_rate_hz` (random phase per pixel);
* shot noise: Poisson events of random polarity at `shot_noise_rate_hz` per pixel;
* hot pixels: a fixed random subset fires ON events at `hot_pixel_rate_hz`.

The step runs numba kernels on numba's threads (`prange` over blocks of rows, then over
time buckets; nogil): each block emits its events as packed keys and buckets them by
coarse time, then each bucket is counting-sorted by time into the output. The result is
the serial reference's (`step_kernel` and a stable sort by time) to the bit, whatever the
number of threads: the blocks are fixed and the sort is stable. uint8 frames are read
through a per-step table of log levels and low-pass gains (the same numbers). Noise draws
are vectorized numpy with a generator seeded by (seed, step), so the same seed and frames
give the same events whatever the threading. Speed against v2e: `python -m
bench.event_sim_v2e` (docs/event-simulator.md).
"""

from __future__ import annotations

import logging
import math
import threading
from typing import Literal

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator

from rigd.core.events import EventArray

log = logging.getLogger(__name__)

_PARALLEL_LOCK = threading.Lock()
_NO_TABLE = np.zeros((2, 0), np.float64)

F32 = NDArray[np.float32]
Frame = NDArray[np.float32] | NDArray[np.uint8]
"""A frame as the step kernels read it: uint8 as given, any other input as float32."""
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: A change counts as a crossing when it reaches the threshold within this fraction of it:
#: float32 log frames carry ~1e-7 relative error, so a ramp of exactly k*C must give k events.
CROSSING_TOLERANCE = 1e-5
#: Reference intensity (DN) that the model's parameters are expressed in: inputs are scaled
#: so that their full scale maps to this (an 8-bit white).
FULL_SCALE_DN = 255.0


class PixelModelConfig(BaseModel):
    """Parameters of the pixel model; every noise term is off by default."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    threshold: float = Field(0.3, gt=0, description="Contrast threshold C (log units), ON and OFF.")
    threshold_on: float | None = Field(None, gt=0, description="ON threshold; defaults to `threshold`.")
    threshold_off: float | None = Field(None, gt=0, description="OFF threshold; defaults to `threshold`.")
    sigma: float = Field(0.0, ge=0, description="Std of the per-pixel threshold mismatch (log units).")
    min_threshold: float = Field(
        0.01, gt=0, description="Mismatched thresholds are clipped to at least this (log units)."
    )
    refractory_us: int = Field(0, ge=0, description="Dead time after an event, us.")
    lowpass: bool = Field(False, description="Photoreceptor low-pass filter on the log level.")
    lowpass_cutoff_hz: float = Field(
        300.0, gt=0, description="Low-pass 3 dB cutoff at full-scale intensity, Hz (scales with intensity)."
    )
    lowpass_min_fraction: float = Field(
        0.01, gt=0, le=1, description="Cutoff never drops below this fraction of `lowpass_cutoff_hz`."
    )
    leak_rate_hz: float = Field(0.0, ge=0, description="Leak (ON) events per pixel per second.")
    shot_noise_rate_hz: float = Field(0.0, ge=0, description="Shot-noise events per pixel per second.")
    hot_pixel_fraction: float = Field(0.0, ge=0, le=1, description="Fraction of pixels that are hot.")
    hot_pixel_rate_hz: float = Field(100.0, ge=0, description="Event rate of a hot pixel, Hz.")
    input_kind: Literal["linear", "log"] = Field(
        "linear", description="linear: intensity frames (any dtype); log: frames already lin-log'ed."
    )
    full_scale: float | None = Field(
        None, gt=0, description="Input value of white; None: 255 for uint8/float, 65535 for uint16."
    )
    log_eps_dn: float = Field(1.0, gt=0, description="Offset added before the log, DN of 255.")
    lin_log_knee_dn: float = Field(
        20.0, gt=0, description="Below this (DN of 255, offset included) the log is linear."
    )
    seed: int = Field(0, ge=0, description="Seed of every random draw (mismatch, noise).")

    @model_validator(mode="after")
    def _check(self) -> PixelModelConfig:
        if self.lin_log_knee_dn < self.log_eps_dn:
            raise ValueError(
                f"lin_log_knee_dn ({self.lin_log_knee_dn}) must be >= log_eps_dn ({self.log_eps_dn})"
            )
        return self

    @property
    def c_on(self) -> float:
        return self.threshold_on if self.threshold_on is not None else self.threshold

    @property
    def c_off(self) -> float:
        return self.threshold_off if self.threshold_off is not None else self.threshold


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
def _level_gain(v: float, conv: LogInput, prm: StepParams, dt_s: float) -> tuple[float, float]:
    """(log level of input value v, low-pass gain of the step: 1 - exp(-dt / tau); 1 when off)."""
    _leak, lowpass, lowpass_hz, lowpass_min, _refr = prm
    lv, inten = _to_log(v, conv)
    if lowpass:
        frac = max(inten / 255.0, lowpass_min)
        tau = 1.0 / (2.0 * math.pi * lowpass_hz * frac)
        return lv, 1.0 - math.exp(-dt_s / tau)
    return lv, 1.0


@njit(nogil=True, cache=True, inline="always")
def _filtered(lp: float, lv: float, a: float, lowpass: bool) -> float:
    """Log level at the end of the step: the input's, low-passed from `lp` (gain a) if asked."""
    return lp + a * (lv - lp) if lowpass else lv


@njit(nogil=True, cache=True, inline="always")
def _new_level(v: float, conv: LogInput, lp: float, prm: StepParams, dt_s: float) -> float:
    """Log level of a pixel at the end of the step from input value v and the level lp before."""
    lv, a = _level_gain(v, conv, prm, dt_s)
    return _filtered(lp, lv, a, prm[1])


@njit(nogil=True, cache=True)
def _level_table(conv: LogInput, prm: StepParams, dt_s: float) -> F64:  # pragma: no cover - numba
    """(2, 256): `_level_gain` of every uint8 value, as the kernels compute it from float32 frames."""
    table = np.empty((2, 256), np.float64)
    for v in range(256):
        lv, a = _level_gain(np.float32(v), conv, prm, dt_s)  # type: ignore[arg-type]
        table[0, v] = lv
        table[1, v] = a
    return table


@njit(nogil=True, cache=True, inline="always")
def _crossings(
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
def _event_time(m: int, sign: int, c: float, d0: float, slope: float, t0: int, t1: int, dt: float) -> int:
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
        ln = _new_level(frame[i, j], conv, lp, prm, dt_s)
        r = ref[i, j]
        k, sign, c, d0, slope, drift = _crossings(lp, ln, r, thr_on[i, j], thr_off[i, j], leak_rate_hz, dt_s)
        if k > 0:
            if n + k > out_x.shape[0]:
                return n, idx
            lt = last_t[i, j]
            for m in range(1, k + 1):
                te = _event_time(m, sign, c, d0, slope, t0, t1, dt)
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


# The simulator's step runs in two passes over fixed blocks of rows, so that the events
# come out in the order of the reference (stable by time: raster order, then the noise)
# whatever the number of threads. Between passes an event is one int64 key,
# (t - t0 - 1) << KEY_T_SHIFT | y << 17 | x << 1 | (ON), 8 bytes to move:
# 1. emit: each block of rows runs the per-pixel rule, appends its events' keys (raster
#    order) to its own slice of a scratch buffer, counts them per coarse time bucket and
#    advances its pixels' state; a block whose slice is full stops before a pixel and
#    resumes there once the buffer has grown. A finished block sorts its keys by coarse
#    bucket (stable, while they are still in cache) into its slice of a second buffer;
# 2. sort: each coarse bucket gathers its run of keys from every block in order (the
#    noise's last), sorts them by the fine time (counting sort, stable) and unpacks them
#    into its range of the output columns.
# Each pass is a `prange` over blocks (or buckets) calling a per-block kernel; the `_ser`
# twins run the same blocks in order on one thread.

#: Rows of the image are cut into at most this many blocks (the unit of parallel work).
MAX_BLOCKS = 64
#: At most 2**COARSE_BITS coarse time buckets per step.
COARSE_BITS = 7
#: Bit of an event key where its time (relative to the step's start) begins.
KEY_T_SHIFT = 33
#: Steps at least this long (us, ~18 min) run the serial reference (times must fit a key).
MAX_KEYED_SPAN = 1 << 30


@njit(nogil=True, cache=True)
def _emit_block(  # pragma: no cover - numba
    b: int,
    rows: int,
    frame: Frame,
    conv: LogInput,
    px: Pixels,
    prm: StepParams,
    t0: int,
    t1: int,
    shift: int,
    hist: I64,
    filled: I64,
    resume: I64,
    keys: I64,
    bucketed: I64,
    table: F64,
) -> None:
    """Pass 1 for block b (rows [b*rows, (b+1)*rows)) from flat pixel index resume[b].

    A uint8 frame is read through `table` (`_level_table`: log level and low-pass gain
    per value, the same numbers), any other through `_level_gain`.

    Event keys go to keys[b*cap + filled[b]:(b+1)*cap] (cap = len(keys) // len(filled)),
    counted in hist[b]; the arithmetic is `step_kernel`'s. Stops before a pixel whose
    events do not fit, leaving its index in resume[b]; else resume[b] = the block's end
    and the block's keys, sorted by coarse bucket, are in the same slice of `bucketed`.
    """
    level, ref, thr_on, thr_off, last_t = px
    leak_rate_hz = prm[0]
    lowpass = prm[1]
    refractory_us = prm[4]
    use_table = table.shape[1] == 256  # a uint8 frame (else the table is empty)
    h, w = frame.shape
    cap = keys.shape[0] // filled.shape[0]
    lo = b * cap
    n = filled[b]
    dt = float(t1 - t0)
    dt_s = dt * 1e-6
    base = t0 + 1
    i_end = min(h, (b + 1) * rows)
    i0 = resume[b] // w
    j0 = resume[b] - i0 * w
    for i in range(i0, i_end):
        for j in range(j0 if i == i0 else 0, w):
            lp = level[i, j]
            if use_table:
                v = int(frame[i, j])
                ln = _filtered(lp, table[0, v], table[1, v], lowpass)
            else:
                lv, a = _level_gain(frame[i, j], conv, prm, dt_s)
                ln = _filtered(lp, lv, a, lowpass)
            r = ref[i, j]
            k, sign, c, d0, slope, drift = _crossings(
                lp, ln, r, thr_on[i, j], thr_off[i, j], leak_rate_hz, dt_s
            )
            if k > 0:
                if n + k > cap:
                    filled[b] = n
                    resume[b] = i * w + j
                    return
                lt = last_t[i, j]
                pix = (i << 17) | (j << 1) | (1 if sign > 0 else 0)
                for m in range(1, k + 1):
                    te = _event_time(m, sign, c, d0, slope, t0, t1, dt)
                    if te - lt < refractory_us:
                        continue
                    keys[lo + n] = ((te - base) << KEY_T_SHIFT) | pix
                    n += 1
                    hist[b, (te - base) >> shift] += 1
                    lt = te
                last_t[i, j] = lt
                r += sign * k * c
            level[i, j] = ln
            if k > 0 or drift != 0.0:
                ref[i, j] = r - drift
    filled[b] = n
    resume[b] = i_end * w
    _bucket_sort(keys, lo, n, hist[b], shift, bucketed)


@njit(nogil=True, cache=True)
def _bucket_sort(  # pragma: no cover - numba
    keys: I64, lo: int, n: int, counts: I64, shift: int, dst: I64
) -> None:
    """keys[lo:lo+n] into dst[lo:lo+n] by coarse bucket (stable); counts: keys per bucket."""
    pos = np.empty(counts.shape[0], np.int64)
    acc = lo
    for q in range(counts.shape[0]):
        pos[q] = acc
        acc += counts[q]
    sh = KEY_T_SHIFT + shift
    for e in range(lo, lo + n):
        key = keys[e]
        q = key >> sh
        dst[pos[q]] = key
        pos[q] += 1


@njit(nogil=True, cache=True, inline="always")
def _unpack(key: int, base: int, e: int, out: EventOut) -> None:
    ox, oy, op, ot = out
    ox[e] = (key >> 1) & 0xFFFF
    oy[e] = (key >> 17) & 0xFFFF
    op[e] = 1 if key & 1 else -1
    ot[e] = base + (key >> KEY_T_SHIFT)


@njit(nogil=True, cache=True)
def _sort_bucket(  # pragma: no cover - numba
    q: int,
    bounds: I64,
    starts: I64,
    hist: I64,
    base: int,
    shift: int,
    bucketed: I64,
    noise: I64,
    out: EventOut,
) -> None:
    """Pass 2 for coarse bucket q: its keys, from every block's run (starts[b, q], hist[b, q]
    long, in `bucketed`; the last row's in `noise`), sorted by time into out[bounds[q]:bounds[q+1]]."""
    lo = bounds[q]
    n = bounds[q + 1] - lo
    if n == 0:
        return
    n_runs = hist.shape[0]
    span = 1 << shift
    if n == 1 or span == 1:
        e = lo
        for b in range(n_runs):
            src = noise if b == n_runs - 1 else bucketed
            for s in range(starts[b, q], starts[b, q] + hist[b, q]):
                _unpack(src[s], base, e, out)
                e += 1
        return
    if span <= 4 * n + 64:
        mask = span - 1
        counts = np.zeros(span + 1, np.int64)
        for b in range(n_runs):
            src = noise if b == n_runs - 1 else bucketed
            for s in range(starts[b, q], starts[b, q] + hist[b, q]):
                counts[((src[s] >> KEY_T_SHIFT) & mask) + 1] += 1
        for f in range(1, span + 1):
            counts[f] += counts[f - 1]
        # Sort the keys in a local buffer (one write stream per fine bucket, in cache), then
        # unpack them in order (one sequential stream per output column).
        local = np.empty(n, np.int64)
        for b in range(n_runs):
            src = noise if b == n_runs - 1 else bucketed
            for s in range(starts[b, q], starts[b, q] + hist[b, q]):
                key = src[s]
                f = (key >> KEY_T_SHIFT) & mask
                local[counts[f]] = key
                counts[f] += 1
        for e in range(n):
            _unpack(local[e], base, lo + e, out)
        return
    gathered = np.empty(n, np.int64)
    e = 0
    for b in range(n_runs):
        src = noise if b == n_runs - 1 else bucketed
        for s in range(starts[b, q], starts[b, q] + hist[b, q]):
            gathered[e] = src[s]
            e += 1
    order = np.argsort(gathered >> KEY_T_SHIFT, kind="mergesort")
    for e in range(n):
        _unpack(gathered[order[e]], base, lo + e, out)


@njit(nogil=True, cache=True, parallel=True)
def _emit_par(  # pragma: no cover - numba
    frame: Frame,
    conv: LogInput,
    px: Pixels,
    prm: StepParams,
    t0: int,
    t1: int,
    rows: int,
    shift: int,
    hist: I64,
    filled: I64,
    resume: I64,
    keys: I64,
    bucketed: I64,
    table: F64,
) -> None:
    for b in prange(filled.shape[0]):
        _emit_block(b, rows, frame, conv, px, prm, t0, t1, shift, hist, filled, resume, keys, bucketed, table)


@njit(nogil=True, cache=True)
def _emit_ser(  # pragma: no cover - numba
    frame: Frame,
    conv: LogInput,
    px: Pixels,
    prm: StepParams,
    t0: int,
    t1: int,
    rows: int,
    shift: int,
    hist: I64,
    filled: I64,
    resume: I64,
    keys: I64,
    bucketed: I64,
    table: F64,
) -> None:
    for b in range(filled.shape[0]):
        _emit_block(b, rows, frame, conv, px, prm, t0, t1, shift, hist, filled, resume, keys, bucketed, table)


@njit(nogil=True, cache=True, parallel=True)
def _sort_par(  # pragma: no cover - numba
    bounds: I64, starts: I64, hist: I64, base: int, shift: int, bucketed: I64, noise: I64, out: EventOut
) -> None:
    for q in prange(bounds.shape[0] - 1):
        _sort_bucket(q, bounds, starts, hist, base, shift, bucketed, noise, out)


@njit(nogil=True, cache=True)
def _sort_ser(  # pragma: no cover - numba
    bounds: I64, starts: I64, hist: I64, base: int, shift: int, bucketed: I64, noise: I64, out: EventOut
) -> None:
    for q in range(bounds.shape[0] - 1):
        _sort_bucket(q, bounds, starts, hist, base, shift, bucketed, noise, out)


@njit(nogil=True, cache=True)
def _run_offsets(hist: I64, cap: int) -> tuple[I64, I64]:  # pragma: no cover - numba
    """(bounds, starts) of a (runs, buckets) histogram: bucket q's events go to the output's
    [bounds[q], bounds[q + 1]); run b's keys of bucket q start at starts[b, q] (run b of the
    key buffer at b * cap, the last run, the noise's, at 0 of its own array)."""
    n_r, n_q = hist.shape
    bounds = np.empty(n_q + 1, np.int64)
    pos = 0
    for q in range(n_q):
        bounds[q] = pos
        for b in range(n_r):
            pos += hist[b, q]
    bounds[n_q] = pos
    starts = np.empty((n_r, n_q), np.int64)
    for b in range(n_r):
        acc = b * cap if b < n_r - 1 else 0
        for q in range(n_q):
            starts[b, q] = acc
            acc += hist[b, q]
    return bounds, starts


@njit(nogil=True, cache=True)
def _noise_keys(ev: EventOut, base: int, shift: int, counts: I64) -> I64:  # pragma: no cover - numba
    """Keys of extra events (in their order), counted per coarse bucket into `counts`."""
    x, y, p, t = ev
    keys = np.empty(t.shape[0], np.int64)
    for e in range(t.shape[0]):
        rel = t[e] - base
        counts[rel >> shift] += 1
        keys[e] = (
            (rel << KEY_T_SHIFT) | (np.int64(y[e]) << 17) | (np.int64(x[e]) << 1) | (1 if p[e] > 0 else 0)
        )
    return keys


@njit(nogil=True, cache=True)
def _counting_sort(  # pragma: no cover - numba
    x: NDArray[np.uint16], y: NDArray[np.uint16], p: NDArray[np.int8], t: I64, t_lo: int, span: int
) -> tuple[NDArray[np.uint16], NDArray[np.uint16], NDArray[np.int8], I64]:
    """Stable sort by t of events whose times lie in [t_lo, t_lo + span)."""
    n = t.shape[0]
    counts = np.zeros(span + 1, np.int64)
    for i in range(n):
        counts[t[i] - t_lo + 1] += 1
    for b in range(1, span + 1):
        counts[b] += counts[b - 1]
    ox = np.empty(n, np.uint16)
    oy = np.empty(n, np.uint16)
    op = np.empty(n, np.int8)
    ot = np.empty(n, np.int64)
    for i in range(n):
        b = t[i] - t_lo
        dst = counts[b]
        counts[b] += 1
        ox[dst] = x[i]
        oy[dst] = y[i]
        op[dst] = p[i]
        ot[dst] = t[i]
    return ox, oy, op, ot


def _event_arrays(n: int) -> EventOut:
    return np.empty(n, np.uint16), np.empty(n, np.uint16), np.empty(n, np.int8), np.empty(n, np.int64)


def sort_by_time(
    x: NDArray[np.uint16], y: NDArray[np.uint16], p: NDArray[np.int8], t: I64, t_lo: int, t_hi: int
) -> EventArray:
    """Events sorted by time (stable), as new arrays; all t must lie in [t_lo, t_hi].

    Counting sort when the time span is not much larger than the event count (the usual
    case for short steps), else numpy's stable argsort.
    """
    n = t.shape[0]
    if n == 0:
        return EventArray.empty()
    span = t_hi - t_lo + 1
    if span <= 8 * n + 4096:
        return EventArray(*_counting_sort(x, y, p, t, t_lo, span))
    order = np.argsort(t, kind="stable")
    return EventArray(x[order], y[order], p[order], t[order])


class EventSimulator:
    """Per-pixel state of one simulated sensor and the step that turns a new frame into events.

    `step(frame, t_us)` takes the frame at time t_us (strictly after the previous one)
    and returns the events of (t_prev, t_us], sorted by time (stable: raster order, then
    noise). The first call only sets the state and returns no events. The step runs on
    numba's threads (`numba.set_num_threads`; `parallel=False`: on the caller's thread)
    and gives the same events whatever their number. Memory is constant: the state
    (about 48 bytes per pixel) plus a scratch event buffer that grows to the largest
    step seen.
    """

    def __init__(
        self, width: int, height: int, config: PixelModelConfig | None = None, *, parallel: bool = True
    ) -> None:
        if not (0 < width <= 65536 and 0 < height <= 65536):
            raise ValueError(f"EventSimulator: geometry {width}x{height} out of range (1..65536)")
        self.width, self.height = int(width), int(height)
        self.config = config if config is not None else PixelModelConfig()
        cfg = self.config
        shape = (self.height, self.width)
        rng = np.random.default_rng([cfg.seed, 0])
        self.thr_on = np.full(shape, cfg.c_on, np.float64)
        self.thr_off = np.full(shape, cfg.c_off, np.float64)
        if cfg.sigma > 0:
            self.thr_on += rng.normal(0.0, cfg.sigma, shape)
            self.thr_off += rng.normal(0.0, cfg.sigma, shape)
            np.maximum(self.thr_on, cfg.min_threshold, out=self.thr_on)
            np.maximum(self.thr_off, cfg.min_threshold, out=self.thr_off)
        n_pix = self.width * self.height
        n_hot = round(cfg.hot_pixel_fraction * n_pix)
        self.hot_pixels: I64 = np.sort(rng.choice(n_pix, size=n_hot, replace=False)).astype(np.int64)
        # Leak phase: each pixel starts somewhere in its leak cycle, else all would fire at once.
        self._ref_offset = (
            rng.uniform(0.0, 1.0, shape) * self.thr_on if cfg.leak_rate_hz > 0 else np.zeros(shape)
        )
        self.level = np.zeros(shape, np.float64)
        self.ref = np.zeros(shape, np.float64)
        self.last_t = np.full(shape, np.iinfo(np.int64).min // 2, np.int64)
        self.t_us: int | None = None
        self.n_steps = 0
        self._params: StepParams = (
            cfg.leak_rate_hz,
            cfg.lowpass,
            cfg.lowpass_cutoff_hz,
            cfg.lowpass_min_fraction,
            cfg.refractory_us,
        )
        self.parallel = parallel
        self._rows = -(-self.height // min(self.height, MAX_BLOCKS))
        self._n_blocks = -(-self.height // self._rows)
        self._keys = np.empty(self._n_blocks * max(1024, self._rows * self.width // 2), np.int64)
        self._bucketed = np.empty_like(self._keys)
        log.debug(
            "EventSimulator %dx%d: C_on %.3f C_off %.3f sigma %.3f, %d hot pixels",
            self.width,
            self.height,
            cfg.c_on,
            cfg.c_off,
            cfg.sigma,
            n_hot,
        )

    @property
    def initialized(self) -> bool:
        return self.t_us is not None

    def _prepare(self, frame: NDArray[np.generic], t_us: int) -> tuple[Frame, float]:
        """Check one input frame; return it as the kernels read it (uint8 kept, any other
        dtype as float32), with the scale of its values to DN."""
        arr = np.asarray(frame)
        where = f"EventSimulator step {self.n_steps} (t={t_us} us)"
        if arr.shape != (self.height, self.width):
            raise ValueError(
                f"{where}: frame has shape {arr.shape}, expected ({self.height}, {self.width}) "
                "(one channel; convert colour frames to gray first)"
            )
        if arr.dtype.kind not in "uif" or arr.dtype == np.bool_:
            raise ValueError(f"{where}: frame dtype {arr.dtype} is not numeric")
        cfg = self.config
        if cfg.input_kind == "log":
            scale = 1.0
        else:
            full = cfg.full_scale
            if full is None:
                full = float(np.iinfo(arr.dtype).max) if arr.dtype.kind in "ui" else FULL_SCALE_DN
                if arr.dtype.kind in "ui" and arr.dtype.itemsize == 1:
                    full = 255.0
            scale = FULL_SCALE_DN / full
        if arr.dtype == np.uint8:
            return np.ascontiguousarray(arr), scale
        f32 = np.ascontiguousarray(arr, dtype=np.float32)
        if arr.dtype.kind == "f" and not np.isfinite(f32).all():
            raise ValueError(f"{where}: frame has NaN or infinite values")
        return f32, scale

    def reset(self) -> None:
        """Forget the time and the levels; the next step starts a new stream (same thresholds)."""
        self.t_us = None
        self.last_t.fill(np.iinfo(np.int64).min // 2)

    def step(self, frame: NDArray[np.generic], t_us: int) -> EventArray:
        """Events of (previous t, t_us] given the frame at t_us; none on the first call."""
        t = int(t_us)
        arr, scale = self._prepare(frame, t)
        cfg = self.config
        conv: LogInput = (cfg.input_kind == "log", scale, cfg.log_eps_dn, cfg.lin_log_knee_dn)
        if self.t_us is None:
            init_state_kernel(
                arr.astype(np.float32, copy=False), conv, self.level, self.ref, self._ref_offset
            )
            self.t_us = t
            self.n_steps += 1
            return EventArray.empty()
        t0 = self.t_us
        if t <= t0:
            raise ValueError(
                f"EventSimulator step {self.n_steps}: time {t} us is not after the previous frame's "
                f"{t0} us (frame times must increase strictly)"
            )
        noise = self._noise(t0, t)
        # Parallel kernels only when no other simulator is running them (numba's workqueue
        # layer does not take concurrent parallel calls); the serial twins give the same events.
        par = self.parallel and _PARALLEL_LOCK.acquire(blocking=False)
        try:
            events = self._run_passes(arr, conv, t0, t, noise, par)
        finally:
            if par:
                _PARALLEL_LOCK.release()
        self.t_us = t
        self.n_steps += 1
        return events

    def _run_passes(
        self, frame: Frame, conv: LogInput, t0: int, t1: int, noise: EventArray | None, par: bool
    ) -> EventArray:
        """Emit and sort the events of (t0, t1] (see the comments above `_emit_block`)."""
        span = t1 - t0
        if span >= MAX_KEYED_SPAN:
            return self._reference_step(frame.astype(np.float32, copy=False), conv, t0, t1, noise)
        table = _level_table(conv, self._params, span * 1e-6) if frame.dtype == np.uint8 else _NO_TABLE
        bits = max(span - 1, 1).bit_length()
        shift = max(bits - COARSE_BITS, 0)
        n_buckets = ((span - 1) >> shift) + 1
        nb = self._n_blocks
        hist = np.zeros((nb + 1, n_buckets), np.int64)  # the last row: noise
        base = t0 + 1
        noise_sorted = np.empty(0, np.int64)
        if noise is not None:
            extra: EventOut = (noise.x, noise.y, noise.p, noise.t)
            noise_keys = _noise_keys(extra, base, shift, hist[nb])
            noise_sorted = np.empty_like(noise_keys)
            _bucket_sort(noise_keys, 0, noise_keys.shape[0], hist[nb], shift, noise_sorted)
        filled = np.zeros(nb, np.int64)
        resume = np.arange(nb, dtype=np.int64) * (self._rows * self.width)
        end = np.minimum(resume + self._rows * self.width, self.width * self.height)
        px: Pixels = (self.level, self.ref, self.thr_on, self.thr_off, self.last_t)
        emit = _emit_par if par else _emit_ser
        while True:
            emit(
                frame,
                conv,
                px,
                self._params,
                t0,
                t1,
                self._rows,
                shift,
                hist,
                filled,
                resume,
                self._keys,
                self._bucketed,
                table,
            )
            if (resume >= end).all():
                break
            self._grow_keys(filled)
        bounds, starts = _run_offsets(hist, self._keys.shape[0] // nb)
        n = int(bounds[-1])
        if n == 0:
            return EventArray.empty()
        out = _event_arrays(n)
        sort = _sort_par if par else _sort_ser
        sort(bounds, starts, hist, base, shift, self._bucketed, noise_sorted, out)
        return EventArray(*out)

    def _grow_keys(self, filled: I64) -> None:
        """Double every block's slice of the key buffers, keeping what they hold."""
        nb = self._n_blocks
        cap = self._keys.shape[0] // nb
        grown = np.empty(2 * cap * nb, np.int64), np.empty(2 * cap * nb, np.int64)
        for old, new in zip((self._keys, self._bucketed), grown, strict=True):
            for b in range(nb):
                new[2 * cap * b : 2 * cap * b + filled[b]] = old[cap * b : cap * b + filled[b]]
        self._keys, self._bucketed = grown
        log.debug("EventSimulator: event buffer grown to %d per block", 2 * cap)

    def _reference_step(
        self, f32: F32, conv: LogInput, t0: int, t1: int, noise: EventArray | None
    ) -> EventArray:
        """The step by the serial reference kernel and a sort (steps too long for the keys)."""
        px: Pixels = (self.level, self.ref, self.thr_on, self.thr_off, self.last_t)
        out = _event_arrays(max(4096, self.width * self.height // 8))
        n, idx, n_pix = 0, 0, self.width * self.height
        while True:
            n, idx = step_kernel(f32, conv, px, self._params, t0, t1, idx, out, n)
            if idx >= n_pix:
                break
            grown = _event_arrays(2 * out[0].shape[0])
            for old, new in zip(out, grown, strict=True):
                new[:n] = old[:n]  # type: ignore[index]
            out = grown
        x, y, p, tt = out[0][:n], out[1][:n], out[2][:n], out[3][:n]
        if noise is not None:
            x = np.concatenate([x, noise.x])
            y = np.concatenate([y, noise.y])
            p = np.concatenate([p, noise.p])
            tt = np.concatenate([tt, noise.t])
        return sort_by_time(x, y, p, tt, t0 + 1, t1)

    def _noise(self, t0: int, t1: int) -> EventArray | None:
        """Shot-noise and hot-pixel events of (t0, t1], unsorted; None when both are off."""
        cfg = self.config
        shot = cfg.shot_noise_rate_hz > 0
        hot = cfg.hot_pixel_rate_hz > 0 and self.hot_pixels.size > 0
        if not (shot or hot):
            return None
        rng = np.random.default_rng([cfg.seed, 1, self.n_steps])
        dt = t1 - t0
        dt_s = dt * 1e-6
        idx_parts: list[I64] = []
        pol_parts: list[NDArray[np.int8]] = []
        if shot:
            n = int(rng.poisson(cfg.shot_noise_rate_hz * dt_s * self.width * self.height))
            idx_parts.append(rng.integers(0, self.width * self.height, n, dtype=np.int64))
            pol_parts.append((rng.integers(0, 2, n, dtype=np.int8) * 2 - 1).astype(np.int8))
        if hot:
            counts = rng.poisson(cfg.hot_pixel_rate_hz * dt_s, self.hot_pixels.size)
            idx_parts.append(np.repeat(self.hot_pixels, counts))
            pol_parts.append(np.ones(int(counts.sum()), np.int8))
        idx = np.concatenate(idx_parts)
        t = t0 + 1 + rng.integers(0, dt, idx.size, dtype=np.int64)
        y, x = np.divmod(idx, self.width)
        return EventArray(x.astype(np.uint16), y.astype(np.uint16), np.concatenate(pol_parts), t)
