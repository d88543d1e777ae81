"""Frames to events: sub-stepping between input frames, frame readers, and a take writer.

`EventSimulator` (event_model.py) is exact for a pixel whose log level moves linearly
between two frames. Video is not like that when things move more than about a pixel
between frames: an edge sweeping over a pixel is a step, not a ramp. So, as in ESIM, the
interval between two input frames is cut into sub-steps short enough that motion per
sub-step stays under a bound, and the intermediate frames are interpolated by warping
both frames along the optical flow (OpenCV DIS), with the bidirectional flow
approximation of Super SloMo. The user picks the trade: a fixed number of sub-steps, or
an error bound (max pixels of motion per sub-step); the number used is reported per
frame pair.

Everything streams: one frame pair at a time, so memory does not grow with the length
of the input (hours of video are fine). The inputs (video, image folder, take, arrays) are
read by frame_sources.py.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from firmware_sim.event_model import EventSimulator, PixelModelConfig
from firmware_sim.frame_sources import FrameSource
from rigd.core.devices import DeviceInfo
from rigd.core.events import EventArray
from rigd.core.frames import Frame
from rigd.core.schema import SyncReport
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.evt import Evt3Encoder, RawHeader
from rigd.take.seal import fail_take, finalize_take
from rigd.take.writer import TakeWriter

log = logging.getLogger(__name__)

F32 = NDArray[np.float32]
AnyFrame = NDArray[Any]

#: Flow is computed on frames at most this wide (downscaled), then scaled back up: the
#: motion estimate only has to be good to a fraction of the sub-step bound.
FLOW_MAX_WIDTH = 640
#: Frames for the flow are padded (edges replicated) to at least this size: DIS picks its
#: number of pyramid levels from the image size, and small images otherwise get too few
#: levels to see motions of tens of pixels.
FLOW_MIN_SIDE = 512
#: Border left out of the motion measure, px of the flow image (DIS is unreliable within
#: about two patches of the edge, where content enters and leaves).
FLOW_BORDER_PX = 16
#: Image file extensions read from a folder.
#: Names inside takes written by `simulate_to_take`.
EVENT_SENSOR_NAME = "ev0"
CAMERA_NAME = "cam0"


# --- frame preparation -------------------------------------------------------------------


def to_gray(frame: AnyFrame, index: int, size: tuple[int, int] | None = None) -> AnyFrame:
    """One-channel frame (RGB/RGBA assumed for colour), resized to size=(width, height) if given.

    The dtype is kept (uint8, uint16, float32; float64 becomes float32) so the pixel model
    can tell the input's full scale.
    """
    arr = np.asarray(frame)
    if arr.dtype == np.float64:
        arr = arr.astype(np.float32)
    if arr.dtype.kind not in "uif" or arr.dtype == np.bool_:
        raise ValueError(f"frame {index}: dtype {arr.dtype} is not numeric")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.ndim == 3:
        if arr.shape[2] not in (3, 4):
            raise ValueError(f"frame {index}: shape {arr.shape} has {arr.shape[2]} channels (want 1, 3 or 4)")
        if arr.dtype not in (np.uint8, np.uint16, np.float32):
            arr = arr.astype(np.float32)
        code = cv2.COLOR_RGB2GRAY if arr.shape[2] == 3 else cv2.COLOR_RGBA2GRAY
        arr = cv2.cvtColor(np.ascontiguousarray(arr), code)
    elif arr.ndim != 2:
        raise ValueError(f"frame {index}: shape {arr.shape} is not (H, W) or (H, W, C)")
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ValueError(f"frame {index}: empty frame of shape {arr.shape}")
    if size is not None and (arr.shape[1], arr.shape[0]) != size:
        if arr.dtype.kind not in "uf" or arr.dtype.itemsize > 4:
            arr = arr.astype(np.float32)
        arr = cv2.resize(arr, size, interpolation=cv2.INTER_AREA)
    return arr


def _flow_u8(a: F32, b: F32) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """The two frames of a pair as 8-bit images on a common scale, for the flow."""
    lo = min(float(a.min()), float(b.min()))
    hi = max(float(a.max()), float(b.max()))
    k = 255.0 / (hi - lo) if hi > lo else 0.0
    ua = np.asarray(cv2.convertScaleAbs(a, alpha=k, beta=-lo * k), np.uint8)
    ub = np.asarray(cv2.convertScaleAbs(b, alpha=k, beta=-lo * k), np.uint8)
    return ua, ub


# --- sub-stepping --------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class StepResult:
    """Events between input frame `index - 1` and `index` (none for frame 0)."""

    index: int
    t_us: int
    events: EventArray
    n_substeps: int
    """Pixel-model steps used for this frame pair (1: no interpolation)."""
    motion_px: float
    """Measured motion between the two frames (max of the flow), NaN when not measured."""


class FramesToEvents:
    """Streams frames through an `EventSimulator`, interpolating sub-steps where motion is fast.

    Exactly one of `substeps` (fixed count per frame pair) or `max_px_per_step` (error
    bound: sub-steps = ceil(motion / bound), capped by `max_substeps`) applies; with
    neither, the bound is 1 px. Frames may be colour (RGB) or gray, any numeric dtype,
    and are resized to (width, height) when they differ.
    """

    def __init__(
        self,
        width: int,
        height: int,
        config: PixelModelConfig | None = None,
        *,
        substeps: int | None = None,
        max_px_per_step: float | None = None,
        max_substeps: int = 64,
    ) -> None:
        if substeps is not None and max_px_per_step is not None:
            raise ValueError("give either substeps or max_px_per_step, not both")
        if substeps is not None and substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        if max_px_per_step is not None and not (max_px_per_step > 0 and math.isfinite(max_px_per_step)):
            raise ValueError(f"max_px_per_step must be a positive number, got {max_px_per_step}")
        if max_substeps < 1:
            raise ValueError(f"max_substeps must be >= 1, got {max_substeps}")
        self.width, self.height = int(width), int(height)
        self.sim = EventSimulator(self.width, self.height, config)
        self.substeps = substeps
        self.max_px_per_step = 1.0 if substeps is None and max_px_per_step is None else max_px_per_step
        self.max_substeps = max_substeps
        self._prev: AnyFrame | None = None
        self._prev_t: int | None = None
        self._index = 0
        self._flow_scale = min(1.0, FLOW_MAX_WIDTH / self.width)
        self._fw = max(8, round(self.width * self._flow_scale))
        self._fh = max(8, round(self.height * self._flow_scale))
        self._dis: Any = None
        self._grid: tuple[F32, F32] | None = None
        self.substeps_total = 0
        self.substeps_max = 0
        self.capped_steps = 0
        """Frame steps whose motion asked for more than `max_substeps` (their events are coarser
        in time than `max_px_per_step` promises; the caller warns once with the count)."""
        self.capped_motion_px = 0.0
        """The largest motion (px) among the capped steps."""

    @property
    def size(self) -> tuple[int, int]:
        return self.width, self.height

    def _flow(self, a: AnyFrame, b: AnyFrame) -> F32:
        """Dense flow a -> b at full resolution, in pixels, (H, W, 2) float32."""
        if self._dis is None:
            self._dis = cv2.DISOpticalFlow_create(  # type: ignore[attr-defined]
                cv2.DISOPTICAL_FLOW_PRESET_FAST
            )
        if self._flow_scale < 1.0 or (self._fw, self._fh) != (self.width, self.height):
            a = cv2.resize(a, (self._fw, self._fh), interpolation=cv2.INTER_AREA)
            b = cv2.resize(b, (self._fw, self._fh), interpolation=cv2.INTER_AREA)
        ua, ub = _flow_u8(np.asarray(a, np.float32), np.asarray(b, np.float32))
        fh, fw = ua.shape
        py, px = max(0, (FLOW_MIN_SIDE - fh + 1) // 2), max(0, (FLOW_MIN_SIDE - fw + 1) // 2)
        if py or px:
            ua = np.asarray(cv2.copyMakeBorder(ua, py, py, px, px, cv2.BORDER_REPLICATE), np.uint8)
            ub = np.asarray(cv2.copyMakeBorder(ub, py, py, px, px, cv2.BORDER_REPLICATE), np.uint8)
        flow = self._dis.calc(ua, ub, None)[py : py + fh, px : px + fw]
        if flow.shape[:2] != (self.height, self.width):
            sx, sy = self.width / flow.shape[1], self.height / flow.shape[0]
            flow = cv2.resize(flow, (self.width, self.height), interpolation=cv2.INTER_LINEAR)
            flow[..., 0] *= sx
            flow[..., 1] *= sy
        return np.asarray(flow, np.float32)

    @staticmethod
    def _motion(flow: F32) -> float:
        """Largest motion of the flow, robust to outliers.

        A 5x5 median removes isolated wrong vectors; a margin at the image border is left
        out, since content entering the image has no correspondence and the flow there is
        unreliable (it would ask for sub-steps the interpolation cannot use anyway).
        """
        mag = cv2.magnitude(flow[..., 0], flow[..., 1])
        h, w = mag.shape
        if min(h, w) >= 5:
            mag = cv2.medianBlur(mag, 5)
        m = min(FLOW_BORDER_PX, (h - 1) // 4, (w - 1) // 4)
        return float(mag[m : h - m, m : w - m].max())

    def _warp(self, img: F32, flow: F32) -> F32:
        """img sampled at (x, y) + flow(x, y) (backward warp), edges replicated."""
        if self._grid is None:
            gx, gy = np.meshgrid(
                np.arange(self.width, dtype=np.float32), np.arange(self.height, dtype=np.float32)
            )
            self._grid = (gx, gy)
        gx, gy = self._grid
        return np.asarray(
            cv2.remap(
                img, gx + flow[..., 0], gy + flow[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
            ),
            np.float32,
        )

    def push(self, frame: AnyFrame, t_us: int) -> StepResult:
        """Feed the next frame (time t_us, strictly increasing) and get the events since the last one."""
        index = self._index
        gray = to_gray(frame, index, self.size)
        t = int(t_us)
        prev, t0 = self._prev, self._prev_t
        if prev is None or t0 is None:
            self.sim.step(gray, t)
            self._prev, self._prev_t, self._index = gray, t, index + 1
            return StepResult(index, t, EventArray.empty(), 0, math.nan)
        if t <= t0:
            raise ValueError(f"frame {index}: time {t} us is not after frame {index - 1} at {t0} us")
        f01: F32 | None = None
        motion = math.nan
        if self.substeps is not None:
            n = self.substeps
        else:
            f01 = self._flow(prev, gray)
            motion = self._motion(f01)
            bound = self.max_px_per_step if self.max_px_per_step is not None else 1.0
            wanted = max(1, math.ceil(motion / bound - 1e-9))
            n = min(wanted, self.max_substeps)
            if wanted > self.max_substeps:
                self.capped_steps += 1
                self.capped_motion_px = max(self.capped_motion_px, motion)
        n = min(n, t - t0)
        parts: list[EventArray] = []
        if n > 1:
            if f01 is None:
                f01 = self._flow(prev, gray)
            f10 = self._flow(gray, prev)
            p32 = np.asarray(prev, np.float32)
            g32 = np.asarray(gray, np.float32)
            for j in range(1, n):
                a = j / n
                # Super SloMo's flows from the intermediate time to each end (no occlusion model).
                ft0 = (-(1.0 - a) * a) * f01 + (a * a) * f10
                ft1 = ((1.0 - a) * (1.0 - a)) * f01 - (a * (1.0 - a)) * f10
                mid = (1.0 - a) * self._warp(p32, ft0) + a * self._warp(g32, ft1)
                tj = t0 + round(j * (t - t0) / n)
                parts.append(self.sim.step(self._match_dtype(mid, gray), tj))
        parts.append(self.sim.step(gray, t))
        events = parts[0] if len(parts) == 1 else EventArray.concatenate(parts)
        self._prev, self._prev_t, self._index = gray, t, index + 1
        self.substeps_total += n
        self.substeps_max = max(self.substeps_max, n)
        if n > 1:
            log.debug("frame %d: motion %.2f px, %d sub-steps, %d events", index, motion, n, len(events))
        return StepResult(index, t, events, n, motion)

    def _match_dtype(self, mid: F32, like: AnyFrame) -> AnyFrame:
        """An interpolated frame of an integer input, as float32 on the model's DN scale.

        Interpolated values are not rounded back to integers (that would add quantisation
        events); the model scales integer inputs by their dtype's range and floats by 255
        unless `full_scale` is set, so the float frame is rescaled to match.
        """
        cfg = self.sim.config
        if like.dtype.kind in "ui" and cfg.input_kind == "linear" and cfg.full_scale is None:
            full = 255.0 if like.dtype.itemsize == 1 else float(np.iinfo(like.dtype).max)
            return (mid * (255.0 / full)).astype(np.float32)
        return mid

    def run(self, frames: Iterable[tuple[AnyFrame, int]]) -> Iterator[StepResult]:
        """Results of every frame of `frames` ((frame, t_us) pairs), one at a time."""
        for frame, t_us in frames:
            yield self.push(frame, t_us)


# --- output to a take ----------------------------------------------------------------------


@dataclass(slots=True)
class SimulationSummary:
    """What one simulate_to_take run produced."""

    path: Path
    frames: int = 0
    events: int = 0
    substeps_total: int = 0
    substeps_max: int = 0
    t_first_us: int | None = None
    t_last_us: int | None = None
    wall_s: float = 0.0

    def record(self, res: StepResult) -> None:
        """Count one written frame and its events."""
        self.frames += 1
        self.events += len(res.events)
        if len(res.events):
            if self.t_first_us is None:
                self.t_first_us = int(res.events.t[0])
            self.t_last_us = int(res.events.t[-1])

    def finish(self, f2e: FramesToEvents, t_start: float) -> None:
        """Take the run's sub-step counts and its wall time since t_start (perf_counter)."""
        self.substeps_total = f2e.substeps_total
        self.substeps_max = f2e.substeps_max
        self.wall_s = time.perf_counter() - t_start


def _steps(
    source: FrameSource,
    f2e: FramesToEvents,
    summary: SimulationSummary,
    on_step: Callable[[StepResult], None] | None,
) -> Iterator[tuple[AnyFrame, StepResult]]:
    """Each frame of `source` with its step through `f2e`, for the caller to write; once the caller
    asks for the next one, the step is counted in `summary` and handed to `on_step`. A source
    without frames is an error (a run must not leave an empty output looking complete)."""
    for frame, t_us in source.frames:
        res = f2e.push(frame, t_us)
        yield frame, res
        summary.record(res)
        if on_step is not None:
            on_step(res)
    if summary.frames == 0:
        raise ValueError(f"{source.description}: no frames")


def simulate_to_take(
    source: FrameSource,
    out: str | Path,
    f2e: FramesToEvents,
    *,
    with_frames: bool = False,
    on_step: Callable[[StepResult], None] | None = None,
    writer_config: WriterConfig | None = None,
    version: str = "sim",
) -> SimulationSummary:
    """Run `source` through `f2e` and write the events (and the frames if asked) to a new take.

    The take's time domain is the simulation time: every device gets the identity clock
    map, so stored times are the input frame times. An exception marks the take failed
    (with the reason) and propagates.
    """
    outp = Path(out)
    cfg = f2e.sim.config
    settings = {
        "pixel_model": cfg.model_dump(),
        "substeps": f2e.substeps,
        "max_px_per_step": f2e.max_px_per_step,
        "max_substeps": f2e.max_substeps,
    }
    rig_json = json.dumps({"name": "simulate-events", "source": source.description, "simulator": settings})
    summary = SimulationSummary(outp)
    t_start = time.perf_counter()
    try:
        _write_take(
            source, outp, f2e, rig_json, settings, summary, with_frames, on_step, writer_config, version
        )
    finally:
        source.close()
    summary.finish(f2e, t_start)
    log.info(
        "simulated %d frames -> %d events into %s in %.1f s",
        summary.frames,
        summary.events,
        outp,
        summary.wall_s,
    )
    return summary


def simulate_to_raw(
    source: FrameSource,
    out: str | Path,
    f2e: FramesToEvents,
    *,
    on_step: Callable[[StepResult], None] | None = None,
) -> SimulationSummary:
    """Like `simulate_to_take`, but write the EVT 3.0 byte stream a Prophesee camera would, as
    a RAW file (streaming: the encoder keeps its state between frames)."""
    outp = Path(out)
    if outp.exists():
        raise ValueError(f"{outp} exists; not overwriting")
    w, h = f2e.size
    summary = SimulationSummary(outp)
    t_start = time.perf_counter()
    encoder = Evt3Encoder()
    header = RawHeader(fmt="evt3", width=w, height=h, fields={"camera_integrator_name": "rigd-sim"})
    try:
        with outp.open("wb") as f:
            f.write(header.to_bytes())
            for _, res in _steps(source, f2e, summary, on_step):
                f.write(encoder.encode(res.events))
    finally:
        source.close()
    summary.finish(f2e, t_start)
    return summary


def _write_take(
    source: FrameSource,
    outp: Path,
    f2e: FramesToEvents,
    rig_json: str,
    settings: dict[str, Any],
    summary: SimulationSummary,
    with_frames: bool,
    on_step: Callable[[StepResult], None] | None,
    writer_config: WriterConfig | None,
    version: str,
) -> None:
    w, h = f2e.size
    with TakeWriter(
        outp,
        rig_config_json=rig_json,
        take_id=outp.stem,
        config=writer_config or WriterConfig(),
        rigd_version=version,
    ) as writer:
        try:
            writer.add_event_sensor(
                EVENT_SENSOR_NAME,
                DeviceInfo(
                    kind="event_sensor",
                    spec=f"simulate-events://{source.description}",
                    vendor="rigd-sim",
                    model="EventSimulator",
                ),
                w,
                h,
                json.dumps(settings),
            )
            cam_shape: tuple[int, ...] | None = None
            for frame, res in _steps(source, f2e, summary, on_step):
                if with_frames:
                    img = np.asarray(frame)
                    if (img.shape[1], img.shape[0]) != (w, h):
                        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
                    if cam_shape is None:
                        cam_shape = img.shape
                        writer.add_camera(
                            CAMERA_NAME,
                            DeviceInfo(kind="rgb_camera", spec=source.description, vendor="rigd-sim"),
                            img.shape,
                            img.dtype,
                            "{}",
                        )
                    writer.append_frame(
                        CAMERA_NAME, Frame(img, res.t_us, 0, res.index, time.monotonic_ns(), -1)
                    )
                writer.append_events(EVENT_SENSOR_NAME, res.events)
            maps = {EVENT_SENSOR_NAME: ClockMap.identity()}
            if cam_shape is not None:
                maps[CAMERA_NAME] = ClockMap.identity()
            report = SyncReport(
                rate_hz=source.fps or 0.0,
                n_pulses=0,
                t_first_pulse_us=None,
                t_last_pulse_us=None,
                warnings=["simulated take: times are simulation time (identity clock maps), no trigger"],
            )
            finalize_take(writer, maps, {}, report)
        except BaseException as exc:
            fail_take(writer, f"simulate-events failed: {exc!r}")
            raise
