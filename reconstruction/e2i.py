"""Events -> intensity: per-pixel integrators (direct, high-pass, complementary) and snapshots.

Each event says "log intensity at this pixel moved by +-C". The three filters of Scheerlinck et al.
("Continuous-time intensity estimation using event cameras", ACCV 2018) integrate that per pixel,
asynchronously, in the log domain:

* direct integration: L += c * p. Exact with a perfect sensor and a known start image, but noise
  and threshold mismatch accumulate as drift for ever.
* high-pass filter: dL/dt = E(t) - alpha * L, i.e. between events L decays to 0 with
  alpha = 2 pi f_c (`cutoff_hz`): drift is forgotten after ~1/alpha, and with it the static scene;
  what remains is the recent change (edges of moving things).
* complementary filter: dL/dt = E(t) - alpha * (L - L_F), with L_F the log of the latest RGB/gray
  frame: low frequencies come from the frames, high frequencies from the events. Needs a
  co-located (registered) camera.

Per event the update is exact for the ODE with piecewise-constant L_F:
L <- e^{-alpha dt} L + (1 - e^{-alpha dt}) L_F + c p, dt = time since the pixel's last update.
The per-event work is one numba nogil kernel; snapshots and frame switches propagate every pixel to
the same time with a vectorized numpy expression. `contrast` is the sensor's contrast threshold in
log units (0.3 in the paper, the simulator's `threshold`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Literal

import numpy as np
from numba import njit
from numpy.typing import NDArray

from rigd.core.events import EventArray

log = logging.getLogger(__name__)

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
Method = Literal["direct", "highpass", "complementary"]
METHODS: tuple[Method, ...] = ("direct", "highpass", "complementary")

#: lin-log of the pixel model (firmware_sim.scene): log(I + eps) above the knee, its tangent below.
LOG_EPS_DN = 1.0
LIN_LOG_KNEE_DN = 20.0


def log_intensity(img: NDArray[np.generic], eps: float = LOG_EPS_DN, knee: float = LIN_LOG_KNEE_DN) -> F64:
    """Lin-log of a linear intensity image (DN 0..255), the quantity the event pixels see."""
    u = np.asarray(img, np.float64) + eps
    lk = math.log(knee)
    return np.where(u >= knee, np.log(np.maximum(u, 1e-12)), lk + (u - knee) / knee)


def linear_intensity(
    logimg: NDArray[np.generic], eps: float = LOG_EPS_DN, knee: float = LIN_LOG_KNEE_DN
) -> F64:
    """Inverse of `log_intensity`, clipped at 0 DN."""
    lv = np.asarray(logimg, np.float64)
    lk = math.log(knee)
    lin = np.where(lv >= lk, np.exp(np.minimum(lv, 50.0)) - eps, (lv - lk) * knee + knee - eps)
    return np.maximum(lin, 0.0)


@njit(nogil=True, cache=True)
def _integrate_kernel(  # pragma: no cover - numba
    x: NDArray[np.uint16],
    y: NDArray[np.uint16],
    p: NDArray[np.int8],
    t: NDArray[np.int64],
    level: F64,
    t_last: NDArray[np.int64],
    frame_log: F64,
    alpha_per_us: float,
    c_on: float,
    c_off: float,
    mode: int,
) -> None:
    """mode 0 direct, 1 high-pass (frame_log ignored, target 0), 2 complementary (target frame_log)."""
    for i in range(t.shape[0]):
        xi = np.int64(x[i])
        yi = np.int64(y[i])
        step = c_on if p[i] > 0 else -c_off
        if mode == 0:
            level[yi, xi] += step
        else:
            dt = t[i] - t_last[yi, xi]
            decay = math.exp(-alpha_per_us * dt) if dt > 0 else 1.0
            target = frame_log[yi, xi] if mode == 2 else 0.0
            level[yi, xi] = decay * level[yi, xi] + (1.0 - decay) * target + step
            t_last[yi, xi] = t[i]


class EventIntegrator:
    """Per-pixel log-intensity state fed by events (and frames for the complementary filter).

    Call order: `process(events)` with time-sorted chunks, `set_frame(image, t_us)` whenever a new
    frame arrives (complementary; for the others it resets the state to the frame, i.e. the start
    image), `snapshot(t_us)` for the log image at any time not before the last processed event.
    """

    def __init__(
        self,
        width: int,
        height: int,
        method: Method = "highpass",
        *,
        contrast: float = 0.3,
        contrast_off: float | None = None,
        cutoff_hz: float = 5.0,
        t0_us: int = 0,
    ) -> None:
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; choose one of {METHODS}")
        if not contrast > 0 or (contrast_off is not None and not contrast_off > 0):
            raise ValueError("contrast thresholds must be positive")
        if method != "direct" and not cutoff_hz > 0:
            raise ValueError(f"cutoff_hz must be positive, got {cutoff_hz}")
        self.width, self.height, self.method = int(width), int(height), method
        self.c_on = float(contrast)
        self.c_off = float(contrast_off if contrast_off is not None else contrast)
        self.cutoff_hz = float(cutoff_hz)
        self.alpha_per_us = 2.0 * math.pi * self.cutoff_hz * 1e-6 if method != "direct" else 0.0
        self.level = np.zeros((self.height, self.width), np.float64)
        self.frame_log = np.zeros((self.height, self.width), np.float64)
        self.t_last = np.full((self.height, self.width), int(t0_us), np.int64)
        self.t_us = int(t0_us)
        self._has_frame = False

    def _mode(self) -> int:
        return METHODS.index(self.method)

    def _propagate(self, t_us: int) -> None:
        """Bring every pixel to time t_us (no events in between): exact decay toward the target."""
        if self.method == "direct":
            self.t_last.fill(t_us)
            return
        dt = (t_us - self.t_last).astype(np.float64)
        decay = np.exp(-self.alpha_per_us * np.maximum(dt, 0.0))
        target = self.frame_log if self.method == "complementary" else 0.0
        self.level = decay * self.level + (1.0 - decay) * target
        self.t_last.fill(t_us)

    def process(self, events: EventArray) -> None:
        if len(events) == 0:
            return
        if int(events.t[0]) < self.t_us:
            raise ValueError(
                f"events at {int(events.t[0])} us are before the integrator's time {self.t_us} us"
            )
        _integrate_kernel(
            events.x,
            events.y,
            events.p,
            events.t,
            self.level,
            self.t_last,
            self.frame_log,
            self.alpha_per_us,
            self.c_on,
            self.c_off,
            self._mode(),
        )
        self.t_us = int(events.t[-1])

    def set_frame(self, image_linear: NDArray[np.generic], t_us: int) -> None:
        """A new frame (linear DN, registered to the sensor) at t_us.

        Complementary: the new low-frequency reference. Direct / high-pass: the state restarts
        from the frame's log (direct integration's start image; high-pass then decays it away).
        """
        t = int(t_us)
        lf = log_intensity(image_linear)
        if lf.shape != self.level.shape:
            raise ValueError(f"frame shape {lf.shape} is not the sensor's {self.level.shape}")
        if self.method == "complementary":
            self._propagate(t)
            self.frame_log = lf
            if not self._has_frame:  # the first frame is also the start image
                self.level = lf.copy()
                self._has_frame = True
        else:
            self.level = lf.copy()
            self.t_last.fill(t)
        self.t_us = max(self.t_us, t)

    def snapshot(self, t_us: int) -> F64:
        """Log-intensity image at t_us (>= the last event processed)."""
        t = int(t_us)
        if t < self.t_us:
            raise ValueError(f"snapshot at {t} us is before the last processed time {self.t_us} us")
        self._propagate(t)
        self.t_us = t
        return self.level.copy()


def reconstruct(
    events: EventArray,
    width: int,
    height: int,
    times_us: Sequence[int] | NDArray[np.int64],
    method: Method = "highpass",
    *,
    frames: Sequence[NDArray[np.generic]] | NDArray[np.generic] | None = None,
    frame_times_us: Sequence[int] | NDArray[np.int64] | None = None,
    contrast: float = 0.3,
    cutoff_hz: float = 5.0,
    init_frame: NDArray[np.generic] | None = None,
) -> F32:
    """(N, H, W) log-intensity snapshots at `times_us` (sorted) from time-sorted events.

    The only Python loop is over breakpoints (snapshot and frame times); events between two
    breakpoints go to the numba kernel in one call. `frames` (linear DN) are required for the
    complementary filter; `init_frame` is the start image for direct / high-pass integration.
    """
    times = np.asarray(times_us, np.int64)
    if times.size and (np.diff(times) < 0).any():
        raise ValueError("snapshot times must be sorted")
    ftimes = np.asarray(frame_times_us if frame_times_us is not None else [], np.int64)
    if method == "complementary" and (frames is None or ftimes.size == 0):
        raise ValueError("the complementary filter needs frames and frame_times_us")
    n_frames = 0 if frames is None else len(frames)
    if n_frames != ftimes.size:
        raise ValueError(f"{n_frames} frames but {ftimes.size} frame times")
    t_start = int(min(events.t[0] if len(events) else 0, times[0] if times.size else 0))
    if ftimes.size:
        t_start = min(t_start, int(ftimes[0]))
    integ = EventIntegrator(width, height, method, contrast=contrast, cutoff_hz=cutoff_hz, t0_us=t_start)
    if init_frame is not None and method != "complementary":
        integ.set_frame(init_frame, t_start)
    # Breakpoints: (time, kind, index), frames before snapshots at equal times.
    marks = sorted(
        [(int(t), 0, i) for i, t in enumerate(ftimes) if method == "complementary"]
        + [(int(t), 1, i) for i, t in enumerate(times)]
    )
    out = np.empty((times.size, height, width), np.float32)
    pos = 0
    for t, kind, i in marks:
        stop = int(np.searchsorted(events.t, t, side="right"))
        if stop > pos:
            integ.process(events[pos:stop])
            pos = stop
        if kind == 0:
            assert frames is not None
            integ.set_frame(frames[i], t)
        else:
            out[i] = integ.snapshot(t)
    log.debug("e2i %s: %d snapshots from %d events", method, times.size, pos)
    return out
