"""Event-guided frame interpolation: the measurable stand-in for the 4D trainer.

The paper's protocol: frames at half the rate (15 FPS) plus events must predict the held-out
frames of the 30 FPS sequence. Methods, all predicting frame t in (t0, t1) from F0, F1:

* `nearest`: the temporally nearest input frame (what a frame-only trainer sees).
* `blend`: (1 - s) F0 + s F1, s = (t - t0) / (t1 - t0).
* `flow`: frame-only flow (DIS), Super SloMo's linear-motion approximation of the intermediate
  flows F_t->0 = -(1 - s) s F01 + s^2 F10 and F_t->1 = (1 - s)^2 F01 - s (1 - s) F10, backward warps
  blended with weights (1 - s, s).
* `events`: two-sided event integration: log F0 plus the events of (t0, t] times the contrast, and
  log F1 minus the events of (t, t1], blended (1 - s, s) in the log domain. Uses the events'
  microsecond timing directly, so fast motion that no flow between frames can follow is kept.
"""

from __future__ import annotations

import logging
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from reconstruction.e2i import linear_intensity, log_intensity
from reconstruction.flow import FlowEstimator, Preset, backward_warp
from reconstruction.representations import event_frame
from rigd.core.events import EventArray

log = logging.getLogger(__name__)

F32 = NDArray[np.float32]
Method = Literal["nearest", "blend", "flow", "events"]
METHODS: tuple[Method, ...] = ("nearest", "blend", "flow", "events")


def interpolate(
    f0: NDArray[np.generic],
    f1: NDArray[np.generic],
    t0_us: int,
    t1_us: int,
    t_us: int,
    method: Method = "events",
    *,
    events: EventArray | None = None,
    contrast: float = 0.3,
    flow_preset: Preset = "dis_medium",
) -> F32:
    """The frame at t_us (linear DN, like the inputs) between frames f0 at t0 and f1 at t1."""
    if not t0_us <= t_us <= t1_us or t1_us <= t0_us:
        raise ValueError(f"need t0 <= t <= t1 and t0 < t1, got {t0_us}, {t_us}, {t1_us}")
    a = np.asarray(f0, np.float32)
    b = np.asarray(f1, np.float32)
    s = (t_us - t0_us) / (t1_us - t0_us)
    if method == "nearest":
        return (a if s <= 0.5 else b).copy()
    if method == "blend":
        return ((1 - s) * a + s * b).astype(np.float32)
    if method == "flow":
        est = FlowEstimator(flow_preset)
        f01, f10 = est(a, b), est(b, a)
        ft0 = -(1 - s) * s * f01 + s * s * f10
        ft1 = (1 - s) ** 2 * f01 - s * (1 - s) * f10
        return ((1 - s) * backward_warp(a, ft0) + s * backward_warp(b, ft1)).astype(np.float32)
    if method == "events":
        if events is None:
            raise ValueError("method 'events' needs the events of (t0, t1]")
        h, w = a.shape
        before = event_frame(events, w, h, t0_us + 1, t_us).astype(np.float64)
        after = event_frame(events, w, h, t_us + 1, t1_us).astype(np.float64) if t_us < t1_us else 0.0
        l_fwd = log_intensity(a) + contrast * before
        l_bwd = log_intensity(b) - contrast * after
        return linear_intensity((1 - s) * l_fwd + s * l_bwd).astype(np.float32)
    raise ValueError(f"unknown method {method!r}; choose one of {METHODS}")
