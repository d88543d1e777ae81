"""Simulated machine-vision camera: one exposure per rising trigger edge, like a GenICam camera.

The wire callback runs on the trigger box's thread, so it only latches the exposure (frame
counter, device timestamp) and queues it; the acquisition thread renders the scene at
mid-exposure, waits for the exposure to end, and puts the frame into a bounded on-camera
buffer. Frames lost to a full buffer or to the `drop_frames` transport fault are counted and
logged in the ground truth, and show as gaps in the frame counter, as on real cameras.

Fault switches (docs/sim-faults.md): `busy_us` makes the camera ignore trigger edges for a
while after each exposure starts (readout / trigger overlap), and `unplug_at_s` /
`unplug_for_s` take it off the bus for a window kept in the `SimWorld`, so the host's
reopen-by-spec finds it gone, then back on the same clock.
"""

from __future__ import annotations

import json
import logging
import math
import queue
import threading
import time
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from drivers.base import Capability, RgbCamera
from drivers.registry import DeviceSpec
from firmware_sim.clock import Hold
from firmware_sim.placement import Placement, check_ranges, ground_truth_facts, place
from firmware_sim.scene import View
from firmware_sim.spec_params import SimCameraParams, check_params
from firmware_sim.world import DeviceClock, Edge, Unpluggable, truth_journal, wait_for_room
from rigd.core.devices import DeviceInfo
from rigd.core.errors import ConfigError
from rigd.core.frames import Frame
from rigd.core.pixels import PIXEL_FORMATS, frame_shape
from rigd.core.settings import CameraSettings

log = logging.getLogger(__name__)

_CAPABILITIES = frozenset(
    {
        Capability.HARDWARE_TRIGGER,
        Capability.FREE_RUN,
        Capability.FRAME_COUNTER,
        Capability.DEVICE_TIMESTAMPS,
        Capability.EXPOSURE_CONTROL,
        Capability.COLOR,
    }
)
#: On virtual time a camera runs at most this many frames ahead of its reader.
_VIRTUAL_LEAD_FRAMES = 4
#: Exposure at which the rendered image has its nominal brightness.
_NOMINAL_EXPOSURE_US = 8000


@dataclass(frozen=True, slots=True)
class CameraParams:
    """What a camera spec may set besides its placement."""

    pixel_format: str = "rgb8"
    buffer_frames: int = 32
    drop_frames: frozenset[int] = field(default_factory=frozenset)
    busy_us: int = 0
    """After an exposure starts, rising edges within this many microseconds are ignored."""
    counter_reset: bool = False
    """After a replug, count frames from 0 again (default: go on from where the unplug left it)."""


@dataclass(frozen=True, slots=True)
class _Exposure:
    counter: int
    true_us: float
    device_us: int
    exposure_us: int
    hold: Hold
    """Keeps a virtual world's time from passing the exposure before its frame is buffered."""


class SimRgbCamera(Unpluggable, RgbCamera):
    """A global-shutter camera in a `SimWorld`, with its own drifting clock.

    The base's acquisition thread is the camera's readout: it completes latched exposures and
    fills the on-camera buffer (the base's queue, `buffer_frames` long; overflow counted as
    `buffer_overflow`). After stop() it finishes the exposures already triggered.
    """

    _device_label = "camera"
    _capabilities = _CAPABILITIES
    _overflow_name = "buffer_overflow"

    def __init__(self, where: Placement, params: CameraParams | None = None) -> None:
        p = params or CameraParams()
        world, name = where.world, where.name
        if p.pixel_format not in PIXEL_FORMATS:
            raise ConfigError(
                f"camera {name}: pixel format {p.pixel_format!r} (use {', '.join(PIXEL_FORMATS)})"
            )
        if p.buffer_frames < 1:
            raise ConfigError(f"camera {name}: buffer_frames must be >= 1, got {p.buffer_frames}")
        if p.busy_us < 0:
            raise ConfigError(f"camera {name}: busy_us must be >= 0, got {p.busy_us}")
        super().__init__(CameraSettings(), queue_len=p.buffer_frames, drain_on_stop=True)
        self._world, self._name, self._scene, self._clock, self._p = world, name, where.scene, where.clock, p
        self._image_hw, self._unplug = (where.height, where.width), where.unplug
        self._label = f"camera {name}"
        self._view: View = where.scene.view(name, where.width, where.height)
        self._info = DeviceInfo(
            kind="rgb_camera",
            spec=where.spec,
            vendor="rigd-sim",
            model="SimRgbCamera",
            serial=f"{world.name}/{name}",
            firmware="sim-1",
            facts=ground_truth_facts(where),
        )
        self._plug_in(world, name, self._info.spec)
        #: First start after a replug goes on counting from where the unplug left the counter.
        self._resume = self._fault.replugged_before(self._opened_us) and not p.counter_reset
        self._busy_until_us = -math.inf
        self._journal = truth_journal()
        self._journal_head = f'{{"world":{json.dumps(world.name)},"dev":{json.dumps(name)},"kind":"frame"'
        world.register_clock(name, where.clock)
        self._lock = threading.Lock()
        self._started = False  # latching edges; under the lock, as the wire callback reads it
        self._next_counter = 0
        self._jobs: queue.SimpleQueue[_Exposure] = queue.SimpleQueue()
        self._free_run: threading.Thread | None = None
        self._stop_free_run = threading.Event()
        self._closing = threading.Event()
        """Set by close(): an exposure still running is abandoned (its frame never leaves)."""
        self._counts = {
            "exposures": 0,
            "transport_dropped": 0,
            "triggers_ignored": 0,
            "unplug_lost": 0,
            "closed_mid_exposure": 0,
        }
        # Every sim device hears the trigger wire and its unplug fault the same way (two calls
        # alike in the camera and the event sensor, each with its own counters above).
        self._unsubscribe = world.wire.subscribe(self._on_edge)
        self._unlisten = self._fault.listen(self._on_unplug)

    @property
    def clock(self) -> DeviceClock:
        return self._clock

    @property
    def pixel_format(self) -> str:
        return self._settings.pixel_format or self._p.pixel_format

    @property
    def frame_shape(self) -> tuple[int, ...]:
        return frame_shape(*self._image_hw, self.pixel_format)

    @property
    def frame_dtype(self) -> np.dtype[np.generic]:
        return np.dtype(np.uint8)

    # --- lifecycle hooks ------------------------------------------------------------------

    def _do_start(self) -> None:
        with self._lock:
            self._next_counter = self._fault.resume_counter if self._resume else 0
            self._resume = False
            self._busy_until_us = -math.inf
            self._started = True
            self._fault.acquiring = self._settings.trigger_mode == "hardware"
        self._arm_unplug(self._unplug, self._world.now_us(), lost_frames_on_edges=True)
        if self._settings.trigger_mode == "free_run":
            self._stop_free_run.clear()
            self._free_run = threading.Thread(
                target=self._run_free, name=f"sim-cam-{self._name}-freerun", daemon=True
            )
            self._free_run.start()

    def _do_stop(self) -> None:
        with self._lock:
            self._started = False
            if not self._dead(self._world.now_us()):
                # An unplugged camera was still acquiring as far as the edges in its window go.
                self._fault.acquiring = False
        if self._free_run is not None:
            self._stop_free_run.set()
            self._free_run.join()
            self._free_run = None

    def _stop_for_close(self) -> None:
        self._closing.set()  # before the stop joins the acquisition thread, which may be exposing
        super()._stop_for_close()

    def _do_close(self) -> None:
        self._unsubscribe()
        self._unlisten()
        while True:  # exposures latched and never completed must not hold a virtual world's time
            try:
                self._jobs.get_nowait().hold.release()
            except queue.Empty:
                break

    def _read(self, timeout_s: float) -> Frame | None:
        frame = super()._read(timeout_s)
        if frame is None:
            return None
        with self._lock:
            if self._dead(self._world.now_us()):  # unplugged while we waited: this frame is lost too
                self._note_unplug_locked([frame.frame_counter])
                raise self._unplugged_error()
        if self._journal is not None:
            self._journal.write(
                f'{self._journal_head},"counter":{frame.frame_counter},'
                f'"t_device_us":{frame.t_exposure_start_us},"host_time_ns":{self.host_clock.now_ns()}}}'
            )
        return frame

    def _counters(self) -> tuple[int, dict[str, int]]:
        with self._lock:
            counts = dict(self._counts)
        return counts["transport_dropped"] + counts["unplug_lost"] + counts["closed_mid_exposure"], counts

    # --- unplug fault ---------------------------------------------------------------------

    def _note_unplug_locked(self, lost: list[int]) -> None:
        """Log what the unplug cost (caller holds the lock); safe to call more than once."""
        lost.extend(f.frame_counter for f in self._queue.drain())
        if lost:
            self._counts["unplug_lost"] += len(lost)
            self._world.truth.mark_frames_lost(self._name, lost)
        if not self._unplug_noted:
            self._unplug_noted = True
            if self._started:
                self._world.truth.add_unplugged(self._name, self._fault.start_us, self._fault.end_us)
            log.warning("camera %s unplugged; %d buffered frame(s) lost", self._name, len(lost))

    # --- exposure -------------------------------------------------------------------------

    def _on_edge(self, edge: Edge) -> None:
        """Runs on the trigger box's thread: latch the exposure, never render here."""
        if not edge.rising:
            return
        with self._lock:
            if not self._started or self._settings.trigger_mode != "hardware":
                return
            if self._dead(edge.true_us):
                return  # no camera on the wire: the world logs the frame as lost
            if edge.true_us < self._busy_until_us:
                # Still reading out the last frame: a real camera drops the edge ("trigger overlap").
                self._counts["triggers_ignored"] += 1
                self._world.truth.add_ignored_trigger(self._name, edge.pulse_index, edge.true_us)
                log.debug("camera %s busy: pulse %d ignored", self._name, edge.pulse_index)
                return
            self._busy_until_us = edge.true_us + self._p.busy_us
            self._expose(edge.true_us)

    def _expose(self, true_us: float) -> None:
        """Start an exposure at a true time; the caller holds the lock."""
        job = _Exposure(
            self._next_counter,
            true_us,
            self._clock.stamp(true_us),
            self._settings.exposure_us,
            self._world.hold(),
        )
        self._next_counter += 1
        self._fault.resume_counter = self._next_counter
        self._counts["exposures"] += 1
        self._jobs.put(job)

    def _run_free(self) -> None:
        """Free-run: exposures every 1/fps seconds of the camera's own clock."""
        period_dev = 1e6 / self._settings.free_run_fps
        dev0 = self._clock.at(self._world.now_us())
        hold = self._world.hold()
        self._world.clock.start()  # a free-running camera sets a virtual world's time going
        k = 0
        try:
            while True:
                t_true = self._clock.true_at(dev0 + k * period_dev)
                if not hold.sleep_until(t_true, self._stop_free_run):
                    return
                with self._lock:
                    if not self._started or self._dead(t_true):
                        return
                    self._expose(t_true)
                k += 1
        finally:
            hold.release()

    def _grab(self, timeout_s: float) -> None:
        """Acquisition thread: complete the exposures latched so far, waiting up to `timeout_s`
        for the first; each frame lands in the buffer or is counted lost. Returns None, so a
        stopping camera ends once no triggered exposure is left."""
        try:
            job = self._jobs.get(timeout=timeout_s)
        except queue.Empty:
            return None
        while True:
            self._complete(job)
            try:
                job = self._jobs.get_nowait()
            except queue.Empty:
                return None

    def _stopped_or_dead(self) -> bool:
        with self._lock:
            return not self._started or self._dead(self._world.now_us())

    def warm_up(self) -> None:
        """Render one throwaway frame in the camera's pixel format before the take: it compiles
        the sprite blending kernel the readout runs, which on a cold numba cache otherwise takes
        the first exposure's readout (and the GIL) for a while with the trigger running."""
        t_us = float(self._world.now_us())
        if self.pixel_format == "bayer_rg8":
            self._scene.render_bayer(self._view, t_us)
        else:
            self._scene.render(self._view, t_us, gray=self.pixel_format == "mono8")
        super().warm_up()

    def _render(self, job: _Exposure) -> NDArray[np.uint8]:
        fmt, t_mid = self.pixel_format, job.true_us + job.exposure_us / 2.0
        if fmt == "bayer_rg8":
            img = self._scene.render_bayer(self._view, t_mid)  # what a colour filter array lets through
        else:
            img = self._scene.render(self._view, t_mid, gray=fmt == "mono8")
        gain = (job.exposure_us / _NOMINAL_EXPOSURE_US) * 10.0 ** (self._settings.gain_db / 20.0)
        if abs(gain - 1.0) > 1e-3:
            img = np.asarray(cv2.convertScaleAbs(img, alpha=gain), dtype=np.uint8)
        return img

    def _complete(self, job: _Exposure) -> None:
        try:
            self._complete_held(job)
        finally:
            job.hold.release()

    def _complete_held(self, job: _Exposure) -> None:
        truth = self._world.truth
        if job.counter in self._p.drop_frames:
            # Lost in transport: the exposure happened, the host never sees it.
            with self._lock:
                self._counts["transport_dropped"] += 1
            truth.add_frame(self._name, job.counter, job.true_us, delivered=False)
            log.debug("camera %s: frame %d dropped (fault injection)", self._name, job.counter)
            return
        t_end = job.true_us + job.exposure_us
        if self._dead(t_end):
            self._lose_unplugged(job)  # unplugged before the exposure ended: no frame leaves
            return
        image = self._render(job)
        # A frame leaves the sensor only once its exposure is over (or never, once closed).
        if not job.hold.sleep_until(t_end, self._closing):
            with self._lock:
                self._counts["closed_mid_exposure"] += 1
            truth.add_frame(self._name, job.counter, job.true_us, delivered=False)
            log.warning(
                "camera %s: closed during the exposure of frame %d; it is lost", self._name, job.counter
            )
            return
        if self._world.virtual:
            # Virtual time waits for the host to make room instead of losing the frame (not once
            # stopped, when the host may have stopped reading, or unplugged).
            wait_for_room(self._queue, _VIRTUAL_LEAD_FRAMES, self._stopped_or_dead)
        frame = Frame(
            image=image,
            t_exposure_start_us=job.device_us,
            exposure_us=job.exposure_us,
            frame_counter=job.counter,
            host_time_ns=self.host_clock.now_ns(),
            pixel_format=self.pixel_format,
        )
        with self._lock:
            # Under the lock, so an unplug noted meanwhile sees this frame in the buffer or not at all.
            dead = self._dead(self._world.now_us())
            if not dead:
                queued = self._queue.put(frame) is None
                truth.add_frame(self._name, job.counter, job.true_us, delivered=queued)
                if queued:
                    return
        if dead:
            self._lose_unplugged(job)
        else:
            log.warning("camera %s: frame buffer full, frame %d dropped", self._name, job.counter)

    def _lose_unplugged(self, job: _Exposure) -> None:
        with self._lock:
            self._counts["unplug_lost"] += 1
        self._world.truth.add_frame(self._name, job.counter, job.true_us, delivered=False)
        log.debug("camera %s: frame %d lost to the unplug", self._name, job.counter)


def open_sim_camera(spec: DeviceSpec) -> SimRgbCamera:
    """Factory for `sim://<world>/<name>?format=mono8|rgb8|bayer_rg8&buffer_frames=&drop_frames=`
    besides the placement parameters (`firmware_sim.placement`: offset_us, drift_ppm, seed,
    width, height, scene=sprites|board). `bayer_rg8` delivers the RGGB mosaic of the RGB render.

    Fault switches: `busy_us=`, `unplug_at_s=`, `unplug_for_s=`, `counter_reset=1`,
    `clock_reset=1`, `open_delay_s=` (docs/sim-faults.md).
    """
    check_params(spec, SimCameraParams, f"camera {spec.path.strip('/') or '?'}")
    where = place(
        spec, {"format", "buffer_frames", "drop_frames", "busy_us", "counter_reset", "open_delay_s"}
    )
    fmt = spec.param("format", "rgb8")
    if fmt not in PIXEL_FORMATS:
        raise ConfigError(f"device spec {spec.raw!r}: format={fmt!r} (use {', '.join(PIXEL_FORMATS)})")
    params = CameraParams(
        pixel_format=fmt,
        buffer_frames=spec.int_param("buffer_frames", 32),
        drop_frames=frozenset(spec.int_list_param("drop_frames")),
        busy_us=spec.int_param("busy_us", 0),
        counter_reset=spec.int_param("counter_reset", 0) == 1,
    )
    check_ranges(
        spec,
        (
            ("buffer_frames", params.buffer_frames >= 1),
            ("busy_us", params.busy_us >= 0),
            ("counter_reset", spec.int_param("counter_reset", 0) in (0, 1)),
        ),
    )
    open_delay_s = spec.float_param("open_delay_s", 0.0)
    if not 0.0 <= open_delay_s <= 600.0:
        raise ConfigError(f"device spec {spec.raw!r}: open_delay_s={open_delay_s!r} out of range (0-600 s)")
    if open_delay_s > 0:
        time.sleep(open_delay_s)  # enumeration, firmware upload, GenICam XML: seconds on real cameras
    return SimRgbCamera(where, params)
