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
import threading
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator

from firmware_sim.keyed_step import (
    COARSE_BITS,
    MAX_BLOCKS,
    MAX_KEYED_SPAN,
    _bucket_sort,
    _emit_par,
    _emit_ser,
    _event_arrays,
    _noise_keys,
    _run_offsets,
    _sort_par,
    _sort_ser,
    sort_by_time,
)
from firmware_sim.pixel_kernels import (
    F32,
    I64,
    EventOut,
    Frame,
    LogInput,
    Pixels,
    StepParams,
    init_state_kernel,
    level_table,
    step_kernel,
)
from rigd.core.events import EventArray

log = logging.getLogger(__name__)

_PARALLEL_LOCK = threading.Lock()
_NO_TABLE = np.zeros((2, 0), np.float64)

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
        table = level_table(conv, self._params, span * 1e-6) if frame.dtype == np.uint8 else _NO_TABLE
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
