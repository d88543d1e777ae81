"""Event-camera intrinsics, e2calib-style: reconstruct frames from events, then calibrate them.

An event sensor has no frames, so (as in e2calib) gray images are reconstructed from the events at
chosen times (the trigger pulses of a take, or a fixed rate), the board is detected in them, and
the ordinary frame calibration (`calibration.intrinsics`) runs on those detections. The
reconstruction method decides both the cost and the accuracy, so several are offered and a
benchmark (`bench/e2calib.py`) tabulates method vs calibration error vs time:

- ``window`` (cheap): signed events of a short window before each time, exponentially decayed
  (a signed time surface). Only the window's events are touched, so the cost scales with the
  number of output frames, not the stream length. It shows where the log intensity *changed*
  recently: the board where it moved in, plus a ghost where it was, so detections are fewer and
  noisier.
- ``hpf`` (medium): per-pixel leaky integration of log intensity over the whole stream, the
  high-pass filter of Scheerlinck et al. (ACCV 2018) without frames:
  L(t) = exp(-a (t - t_last)) L(t_last) + C p at every event. Every event is visited once, in
  order. It recovers the log image up to a slowly decaying history, which the chessboard detector
  (saddle points, sub-pixel refinement on gradients) is insensitive to; with a = 0 it is plain
  direct integration (exact for an ideal sensor, plus the initial scene as a ghost).

- ``integrate`` (accurate): direct integration of the events into log intensity per pixel (exact
  for an ideal sensor up to one contrast step), then per-pixel normalisation by the lowest and
  highest level the pixel reaches over the *whole* stream. A board is black and white, so every
  pixel the board sweeps over has just two rest levels, its dark and its bright one; mapping them
  to 0 and 1 removes the unknown integration constant (the initial scene) that ``hpf`` has to
  forget slowly, and with it the ghost and the slow-decay lag that biased hpf's corners by a few
  milliseconds of board motion (focal errors 0.6-2 % against 0.02-0.1 % here, measured on the
  sim rig). Two passes over the events (min/max, then the images); the normalisation needs the
  whole stream, so it is an offline method.

The contrast threshold C only scales the reconstructed log image, so its exact value does not
matter for detection; ``window`` and ``hpf`` images are mapped to 8 bits by robust percentiles,
``integrate`` images are already in [0, 1].
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numba import njit
from numpy.typing import NDArray
from pydantic import BaseModel

from calibration.boards import BoardSpec, Detection, detect
from calibration.errors import CalibrationError, NoBoardFoundError
from calibration.intrinsics import IntrinsicsResult, RejectedView, calibrate_intrinsics
from rigd.core.events import EventArray

log = logging.getLogger(__name__)

F32 = NDArray[np.float32]
I64 = NDArray[np.int64]

METHODS = ("window", "hpf", "integrate")
#: The method `detect_in_reconstructions` and the rig calibration use by default.
ACCURATE_METHOD = "integrate"

#: Told where a calibration is: (stage, method, done, total); stages "reconstruct" and "calibrate"
#: are not counted (None), "detect" counts the frames searched for the board. A calibration on a
#: long take runs for minutes, and whoever shows it wants to say how far it got.
StageCallback = Callable[[str, str, int | None, int | None], None]


def _quiet(stage: str, method: str, done: int | None, total: int | None) -> None:
    """The default `StageCallback`: callers that show nothing need not pass one."""


@dataclass(frozen=True)
class ReconstructionParams:
    """Tuning of the reconstruction methods (defaults measured on the sim rig's board scene).

    window_us / tau_us: the ``window`` method's window and decay time constant.
    cutoff_hz: the ``hpf`` method's high-pass corner frequency (a = 2 pi cutoff); 0 integrates.
    contrast: log-intensity step of one event (the sensor's threshold; only a scale).
    blur_px: Gaussian sigma applied to the reconstruction, which softens the one-threshold
    quantisation steps that an ideal pixel leaves along edges.
    half_step: the ``hpf`` and ``integrate`` methods' lag correction (see `_leaky_integrate_kernel`).
    integrate_blur_px: Gaussian sigma for ``integrate`` images (their steps are a full contrast
    step of a two-level signal, coarser than hpf's; 1.0-1.2 px measured best for corner accuracy).
    min_range: ``integrate`` pixels whose levels span less than this (log units) never saw both
    colours of the board; they are set to mid-gray instead of amplifying a small difference.
    """

    window_us: int = 150_000
    tau_us: float = 80_000.0
    cutoff_hz: float = 1.0
    contrast: float = 0.3
    blur_px: float = 0.7
    half_step: bool = True
    integrate_blur_px: float = 1.0
    min_range: float = 1.0


@njit(cache=True, nogil=True)
def _leaky_integrate_kernel(  # pragma: no cover - numba
    x: NDArray[np.uint16],
    y: NDArray[np.uint16],
    p: NDArray[np.int8],
    t: I64,
    times: I64,
    alpha_per_us: float,
    contrast: float,
    half_step: bool,
    out: F32,
) -> None:
    """out[i] = the leaky-integrated log image at times[i] (times sorted ascending).

    With `half_step`, half a contrast step in the direction of a pixel's last event is added:
    a pixel fires only once its log intensity has moved a full step, so after an ON event the
    true level lies in [ref, ref + C) and ref + C/2 is its unbiased estimate. Without it every
    moving edge lags behind its true position, a view-dependent bias the calibration cannot absorb.
    """
    n_out, h, w = out.shape
    state = np.zeros((h, w), np.float64)
    t_last = np.zeros((h, w), np.float64)
    last_p = np.zeros((h, w), np.float64)
    if t.shape[0] > 0:
        t_last[:, :] = float(t[0])
    k = 0
    n = t.shape[0]
    for i in range(n_out):
        ts = times[i]
        while k < n and t[k] <= ts:
            xi = x[k]
            yi = y[k]
            tk = float(t[k])
            if alpha_per_us > 0.0:
                state[yi, xi] *= math.exp(-alpha_per_us * (tk - t_last[yi, xi]))
            state[yi, xi] += contrast if p[k] > 0 else -contrast
            last_p[yi, xi] = 1.0 if p[k] > 0 else -1.0
            t_last[yi, xi] = tk
            k += 1
        for r in range(h):
            for c in range(w):
                v = state[r, c]
                if half_step:
                    v += 0.5 * contrast * last_p[r, c]
                if alpha_per_us > 0.0:
                    v *= math.exp(-alpha_per_us * max(float(ts) - t_last[r, c], 0.0))
                out[i, r, c] = v


def reconstruct_hpf(
    events: EventArray, size: tuple[int, int], times_us: Sequence[int] | I64, params: ReconstructionParams
) -> F32:
    """(n, H, W) high-pass-filtered log images at `times_us` (any order), from all events up to each."""
    times = np.asarray(times_us, np.int64)
    order = np.argsort(times, kind="stable")
    w, h = size
    out = np.zeros((times.size, h, w), np.float32)
    alpha = 2.0 * math.pi * params.cutoff_hz * 1e-6
    _leaky_integrate_kernel(
        events.x, events.y, events.p, events.t, times[order], alpha, params.contrast, params.half_step, out
    )
    res = np.empty_like(out)
    res[order] = out
    return res


@njit(cache=True, nogil=True)
def _level_range_kernel(  # pragma: no cover - numba
    x: NDArray[np.uint16],
    y: NDArray[np.uint16],
    p: NDArray[np.int8],
    contrast: float,
    half_step: bool,
    vmin: NDArray[np.float64],
    vmax: NDArray[np.float64],
) -> None:
    """Per-pixel lowest and highest integrated level (vmin, vmax start at the initial level 0)
    over all events, with the same half-step correction as `_integrate_kernel`."""
    h, w = vmin.shape
    state = np.zeros((h, w), np.float64)
    for k in range(x.shape[0]):
        xi = x[k]
        yi = y[k]
        s = 1.0 if p[k] > 0 else -1.0
        state[yi, xi] += s * contrast
        v = state[yi, xi] + (0.5 * contrast * s if half_step else 0.0)
        if v < vmin[yi, xi]:
            vmin[yi, xi] = v
        if v > vmax[yi, xi]:
            vmax[yi, xi] = v


@njit(cache=True, nogil=True)
def _integrate_kernel(  # pragma: no cover - numba
    x: NDArray[np.uint16],
    y: NDArray[np.uint16],
    p: NDArray[np.int8],
    t: I64,
    times: I64,
    contrast: float,
    half_step: bool,
    vmin: NDArray[np.float64],
    vmax: NDArray[np.float64],
    min_range: float,
    out: F32,
) -> None:
    """out[i] = the integrated log level at times[i] (sorted ascending), normalised per pixel to
    (v - vmin) / (vmax - vmin); pixels with vmax - vmin < min_range are 0.5."""
    n_out, h, w = out.shape
    state = np.zeros((h, w), np.float64)
    last_p = np.zeros((h, w), np.float64)
    k = 0
    n = t.shape[0]
    for i in range(n_out):
        ts = times[i]
        while k < n and t[k] <= ts:
            s = 1.0 if p[k] > 0 else -1.0
            state[y[k], x[k]] += s * contrast
            last_p[y[k], x[k]] = s
            k += 1
        for r in range(h):
            for c in range(w):
                rng = vmax[r, c] - vmin[r, c]
                if rng < min_range:
                    out[i, r, c] = 0.5
                    continue
                v = state[r, c]
                if half_step:
                    v += 0.5 * contrast * last_p[r, c]
                out[i, r, c] = (v - vmin[r, c]) / rng


def reconstruct_integrate(
    events: EventArray, size: tuple[int, int], times_us: Sequence[int] | I64, params: ReconstructionParams
) -> F32:
    """(n, H, W) directly integrated log images at `times_us` (any order), each pixel normalised
    by the darkest and brightest level it reaches over the whole stream (0 = dark, 1 = bright)."""
    times = np.asarray(times_us, np.int64)
    order = np.argsort(times, kind="stable")
    w, h = size
    vmin = np.zeros((h, w), np.float64)
    vmax = np.zeros((h, w), np.float64)
    _level_range_kernel(events.x, events.y, events.p, params.contrast, params.half_step, vmin, vmax)
    out = np.zeros((times.size, h, w), np.float32)
    _integrate_kernel(
        events.x,
        events.y,
        events.p,
        events.t,
        times[order],
        params.contrast,
        params.half_step,
        vmin,
        vmax,
        params.min_range,
        out,
    )
    res = np.empty_like(out)
    res[order] = out
    return res


def reconstruct_window(
    events: EventArray, size: tuple[int, int], times_us: Sequence[int] | I64, params: ReconstructionParams
) -> F32:
    """(n, H, W) signed, exponentially decayed sums of the events in [t - window, t]."""
    times = np.asarray(times_us, np.int64)
    w, h = size
    out = np.zeros((times.size, h, w), np.float32)
    for i, ts in enumerate(times):
        lo = int(np.searchsorted(events.t, ts - params.window_us, side="left"))
        hi = int(np.searchsorted(events.t, ts, side="right"))
        if hi <= lo:
            continue
        sl = slice(lo, hi)
        wgt = np.exp(-(ts - events.t[sl]).astype(np.float64) / params.tau_us)
        wgt *= np.where(events.p[sl] > 0, params.contrast, -params.contrast)
        idx = events.y[sl].astype(np.int64) * w + events.x[sl].astype(np.int64)
        out[i] = np.bincount(idx, weights=wgt, minlength=w * h).reshape(h, w).astype(np.float32)
    return out


def reconstruct(
    events: EventArray,
    size: tuple[int, int],
    times_us: Sequence[int] | I64,
    method: str = ACCURATE_METHOD,
    params: ReconstructionParams | None = None,
) -> F32:
    """Log-intensity-like float images (n, H, W) at the given times by `method` (see METHODS)."""
    p = params or ReconstructionParams()
    if method == "hpf":
        return reconstruct_hpf(events, size, times_us, p)
    if method == "window":
        return reconstruct_window(events, size, times_us, p)
    if method == "integrate":
        return reconstruct_integrate(events, size, times_us, p)
    raise CalibrationError(f"unknown reconstruction method {method!r}; choose from {', '.join(METHODS)}")


def to_uint8(img: F32, blur_px: float = 0.7) -> NDArray[np.uint8]:
    """8-bit image for the board detector: optional blur, then the 0.5..99.5 % range stretched to
    0..255 (robust to the few pixels an event burst drives far off)."""
    f = np.asarray(img, np.float32)
    if blur_px > 0:
        f = np.asarray(cv2.GaussianBlur(f, (0, 0), blur_px), np.float32)
    lo, hi = np.percentile(f, [0.5, 99.5])
    if hi - lo < 1e-6:
        return np.full(f.shape, 128, np.uint8)
    return np.clip((f - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)


def detector_image(img: F32, method: str, params: ReconstructionParams) -> NDArray[np.uint8]:
    """The 8-bit image the board detector sees for a reconstruction by `method`: ``integrate``
    images are already normalised to [0, 1] (a percentile stretch would clip the rest levels
    unevenly), the others are stretched by `to_uint8`."""
    if method != "integrate":
        return to_uint8(img, params.blur_px)
    f = np.asarray(img, np.float32)
    if params.integrate_blur_px > 0:
        f = np.asarray(cv2.GaussianBlur(f, (0, 0), params.integrate_blur_px), np.float32)
    return np.clip(f * 255.0 + 0.5, 0, 255).astype(np.uint8)


class MethodResult(BaseModel):
    """One reconstruction method's outcome: frames, detections, calibration (None if it failed),
    and the wall time of each stage in seconds."""

    method: str
    frames: int
    detected: int
    intrinsics: IntrinsicsResult | None
    error: str | None = None
    reconstruct_s: float
    detect_s: float
    calibrate_s: float

    @property
    def total_s(self) -> float:
        return self.reconstruct_s + self.detect_s + self.calibrate_s


class E2CalibResult(BaseModel):
    sensor: str
    board: str
    image_size: tuple[int, int]
    events: int
    times_us: list[int]
    methods: list[MethodResult]

    def best(self) -> MethodResult:
        """The calibrated method with the lowest RMS; CalibrationError when none calibrated."""
        ok = [m for m in self.methods if m.intrinsics is not None]
        if not ok:
            raise CalibrationError(
                f"sensor {self.sensor}: no reconstruction method gave a calibration: "
                + "; ".join(f"{m.method}: {m.error}" for m in self.methods)
            )
        return min(ok, key=lambda m: m.intrinsics.rms_px if m.intrinsics else math.inf)


@dataclass
class FrameDetections:
    """Detections in reconstructed frames, keyed like the times they were made at."""

    detections: dict[str, Detection] = field(default_factory=dict)
    rejected: list[RejectedView] = field(default_factory=list)


def detect_in_reconstructions(
    events: EventArray,
    size: tuple[int, int],
    times_us: Sequence[int] | I64,
    board: BoardSpec,
    method: str = ACCURATE_METHOD,
    params: ReconstructionParams | None = None,
    names: Sequence[str] | None = None,
    sensor: str = "ev",
    on_progress: StageCallback = _quiet,
) -> FrameDetections:
    """Reconstruct at `times_us` and detect the board in each frame; `names` label the views
    (default `<sensor>@<t_us>`); the rig calibration matches views across devices by them."""
    p = params or ReconstructionParams()
    times = np.asarray(times_us, np.int64)
    labels = list(names) if names is not None else _labels(sensor, times)
    if len(labels) != times.size:
        raise CalibrationError(f"{len(labels)} names for {times.size} times")
    on_progress("reconstruct", method, None, None)
    imgs = reconstruct(events, size, times, method, p)
    dets, rejected = _detect_frames(imgs, labels, method, p, board, on_progress)
    return FrameDetections({d.name: d for d in dets}, rejected)


def _labels(sensor: str, times: I64) -> list[str]:
    return [f"{sensor}@{int(t)}" for t in times]


def _detect_frames(
    imgs: F32,
    labels: Sequence[str],
    method: str,
    params: ReconstructionParams,
    board: BoardSpec,
    on_progress: StageCallback = _quiet,
) -> tuple[list[Detection], list[RejectedView]]:
    """The board in each reconstructed frame (named by its label), in order; the misses rejected."""
    dets: list[Detection] = []
    rejected: list[RejectedView] = []
    for i, (name, img) in enumerate(zip(labels, imgs, strict=True)):
        on_progress("detect", method, i, len(labels))
        d = detect(detector_image(img, method, params), board, name=name)
        if d is None:
            rejected.append(RejectedView(name=name, reason=f"board {board} not found in the reconstruction"))
        else:
            dets.append(d)
    return dets, rejected


def calibrate_events(
    events: EventArray,
    size: tuple[int, int],
    times_us: Sequence[int] | I64,
    board: BoardSpec,
    sensor: str = "ev",
    methods: Sequence[str] = METHODS,
    params: ReconstructionParams | None = None,
    model: str = "k1k2",
    max_views: int = 40,
    on_progress: StageCallback = _quiet,
) -> E2CalibResult:
    """Calibrate an event sensor's intrinsics with every method in `methods`.

    `events` must be time-sorted, in the same clock as `times_us`. At most `max_views`
    detections (evenly spread over time) go into the calibration: neighbouring frames of a moving
    board are nearly redundant and the calibration cost grows with the views. A method that finds
    no board or cannot calibrate is reported with its error rather than failing the others.
    """
    p = params or ReconstructionParams()
    times = np.asarray(times_us, np.int64)
    if times.size == 0:
        raise CalibrationError(f"sensor {sensor}: no reconstruction times given")
    if len(events) == 0:
        raise CalibrationError(f"sensor {sensor}: no events to reconstruct frames from")
    results: list[MethodResult] = []
    for m in methods:
        if m not in METHODS:
            raise CalibrationError(f"unknown reconstruction method {m!r}; choose from {', '.join(METHODS)}")
        results.append(
            _calibrate_method(m, events, size, times, board, sensor, p, model, max_views, on_progress)
        )
    return E2CalibResult(
        sensor=sensor,
        board=str(board),
        image_size=size,
        events=len(events),
        times_us=[int(t) for t in times],
        methods=results,
    )


def _calibrate_method(
    method: str,
    events: EventArray,
    size: tuple[int, int],
    times: I64,
    board: BoardSpec,
    sensor: str,
    params: ReconstructionParams,
    model: str,
    max_views: int,
    on_progress: StageCallback = _quiet,
) -> MethodResult:
    """Reconstruct, detect and calibrate with one method, timing each stage."""
    t0 = time.perf_counter()
    on_progress("reconstruct", method, None, None)
    imgs = reconstruct(events, size, times, method, params)
    t1 = time.perf_counter()
    dets, rejected = _detect_frames(imgs, _labels(sensor, times), method, params, board, on_progress)
    on_progress("detect", method, len(imgs), len(imgs))
    t2 = time.perf_counter()
    on_progress("calibrate", method, None, None)
    intr: IntrinsicsResult | None = None
    err: str | None = None
    try:
        if not dets:
            raise NoBoardFoundError(
                f"sensor {sensor}: board {board} not found in any of {times.size} {method} reconstructions"
            )
        intr = calibrate_intrinsics(
            _spread(dets, max_views), board, camera=sensor, model=model, rejected=rejected
        )
    except CalibrationError as exc:
        err = str(exc)
        log.info("sensor %s, method %s: %s", sensor, method, exc)  # in .error: the caller reports it
    t3 = time.perf_counter()
    detected = len(imgs) - len(rejected)
    log.info(
        "sensor %s, method %s: %d/%d frames with the board, RMS %s, %.2f s",
        sensor,
        method,
        detected,
        times.size,
        f"{intr.rms_px:.3f} px" if intr else "-",
        t3 - t0,
    )
    return MethodResult(
        method=method,
        frames=int(times.size),
        detected=detected,
        intrinsics=intr,
        error=err,
        reconstruct_s=t1 - t0,
        detect_s=t2 - t1,
        calibrate_s=t3 - t2,
    )


def _spread(dets: list[Detection], max_views: int) -> list[Detection]:
    """At most `max_views` detections, evenly spread over the sequence."""
    if len(dets) <= max_views:
        return dets
    keep = np.unique(np.linspace(0, len(dets) - 1, max_views).round().astype(int))
    return [dets[i] for i in keep]
