"""`replay:///abs/TAKE.h5?device=NAME`: a recorded take played back as a rig, through the real drivers.

Every device of a recorded take can be opened again from the file: the trigger box runs the
simulated firmware on a pty (the host opens it with pyserial) and reports the recorded pulse
times; a camera delivers the recorded frames with their device timestamps and counters; an
event sensor encodes the recorded events and trigger-in edges, back in its own clock, into an
EVT 3.0 byte stream that the production decoder reads. The devices share one `SimWorld`
per take (and clock: `clock=virtual` replays as fast as the host reads, real time otherwise),
so a re-captured replay holds the same frames and events and ties the same clocks.

Times: the take holds rig times (trigger-box microseconds). When the box is STARTed it puts
the recorded pulse 0 one start lead ahead and fixes `rig = true + shift` for the world; every
device waits for that shift and hands out its data when true time reaches it. Device times come
back exactly: camera exposure starts and trigger-in edges are stored in device time, and an
event's device time is the integer whose rig time (through the take's own clock map) is the
recorded one.

Fault switches as on `sim://` devices (docs/sim-faults.md): box `drop_pulses`, `garbage_every`,
`silent_after`, `garbage_after`; camera `drop_frames`; camera and event sensor `unplug_at_s` /
`unplug_for_s`, and `clock_reset=1` (a device opened after its replug counts from 0).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray

from drivers.base import Capability, RgbCamera
from drivers.evt_stream import DecodingEventSensor
from drivers.lifecycle import END, Signal
from drivers.registry import DeviceSpec
from drivers.serial_trigger import SerialTrigger
from firmware_sim.box_devices import open_box_trigger
from firmware_sim.clock import Hold
from firmware_sim.event_sensor import SLICE_US, _Packet
from firmware_sim.spec_params import ReplayCameraParams, ReplaySensorParams, ReplayTriggerParams, check_params
from firmware_sim.trigger_box import START_LEAD_US, SimTriggerBox
from firmware_sim.world import (
    DeviceClock,
    SimWorld,
    Unpluggable,
    UnplugParams,
    get_world,
    unplug_params,
    wait_for_room,
)
from rigd.core.devices import DeviceInfo
from rigd.core.errors import ConfigError, DeviceError, RigdError
from rigd.core.events import EventArray, TriggerEvents
from rigd.core.frames import Frame
from rigd.core.layout import Frames, TriggerEdges, frame_group, trigger_in_group
from rigd.core.pixels import stored_pixel_format
from rigd.core.schema import DeviceSync, SyncReport
from rigd.core.settings import CameraSettings
from rigd.core.timebase import ClockMap
from rigd.evt import Evt3Encoder
from rigd.take import Take
from rigd.take.h5file import open_checked

log = logging.getLogger(__name__)

SCHEME = "replay"
#: A device runs at most this many buffers ahead of its reader on virtual time.
_VIRTUAL_LEAD = 4
#: Events read from the take at a time by a replayed sensor (whole LZ4 chunks, once each).
_READ_AHEAD = 1 << 20


@dataclass(frozen=True, slots=True)
class CameraTrack:
    """One camera's recorded frames (images stay in the file)."""

    name: str
    rig_us: NDArray[np.int64]
    device_us: NDArray[np.int64]
    counter: NDArray[np.int64]
    exposure_us: NDArray[np.int64]
    shape: tuple[int, ...]
    cmap: ClockMap | None
    """The camera's clock map (None for a camera the sync report has no fit for)."""
    pixel_format: str = "rgb8"
    """As recorded; a Bayer mosaic is replayed as it is."""


@dataclass(frozen=True, slots=True)
class SensorTrack:
    """One event sensor's clock map and trigger-in edges (events stay in the file)."""

    name: str
    width: int
    height: int
    cmap: ClockMap
    trig_rig: NDArray[np.int64]
    trig_device: NDArray[np.int64]
    trig_p: NDArray[np.uint8]
    trig_channel: NDArray[np.uint8]
    n_events: int


#: Rig and device times a replay accepts: within +-2^45 us (about 1.1 years of clock), the
#: headroom the sim's own clocks have (`firmware_sim.spec_params.MAX_OFFSET_US`).
MAX_TIME_US = 2**45
#: A device clock runs within +-1000 ppm of the rig clock (crystals: about +-100 ppm).
MAX_RATE_ERROR = 1e-3
#: The longest take a replay plays (the capture's own bound).
MAX_SPAN_US = 7 * 86400 * 10**6


def _clock_map(sync: DeviceSync) -> ClockMap:
    return ClockMap(sync.device_ref_us, sync.rig_ref_us, sync.rate, sync.frac_us)


def check_clock_map(path: Path, sync: DeviceSync, lo_rig: int, hi_rig: int) -> None:
    """A recorded clock fit must map the take's span to device times a device can have: a
    finite rate near 1 and times within +-MAX_TIME_US (an EVT stream is encoded from time 0 on,
    so a device time of 2^62 would be a terabyte of time words)."""
    where = f"replay {path}: the sync report's clock map of {sync.device}"
    if not (math.isfinite(sync.rate) and abs(sync.rate - 1.0) <= MAX_RATE_ERROR):
        raise ConfigError(
            f"{where} has rate {sync.rate!r}; a device clock runs within 1 +- {MAX_RATE_ERROR:g}"
        )
    if not (math.isfinite(sync.frac_us) and abs(sync.frac_us) <= 1.0):
        raise ConfigError(f"{where} has frac_us {sync.frac_us!r}; it is within +-1 us")
    for name, value in (("device_ref_us", sync.device_ref_us), ("rig_ref_us", sync.rig_ref_us)):
        if abs(value) > MAX_TIME_US:
            raise ConfigError(f"{where} has {name} {value}, outside +-{MAX_TIME_US} us")
    span = _clock_map(sync).to_device(np.array([lo_rig, hi_rig], np.int64))
    if np.abs(span).max() > MAX_TIME_US:
        raise ConfigError(
            f"{where} puts the take's span at device times {int(span[0])}..{int(span[1])} us, "
            f"outside +-{MAX_TIME_US} us"
        )


class Recording:
    """What a finalized take holds that a replay needs, read once per world."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            take = Take(path)
        except RigdError as exc:
            raise ConfigError(f"replay {path}: {exc}") from None
        with take:
            if take.time_domain != "rig":
                raise ConfigError(
                    f"replay {path}: the take is not finalized (times still in device clocks); "
                    "run `rigd recover` on it first"
                )
            report = take.sync_report
            if report is None:
                raise ConfigError(f"replay {path}: the take has no sync report")
            self.rate_hz = float(report.rate_hz)
            pulses = take.pulses()
            order = np.argsort(pulses.index, kind="stable")
            self.pulse_index = pulses.index[order]
            self.pulse_t = pulses.t_us[order]
            if self.pulse_index.size == 0:
                raise ConfigError(f"replay {path}: the take has no trigger pulses to replay")
            self._pulses = dict(zip(self.pulse_index.tolist(), self.pulse_t.tolist(), strict=True))
            lo, hi = int(self.pulse_t.min()), int(self.pulse_t.max())
            if max(abs(lo), abs(hi)) > MAX_TIME_US or hi - lo > MAX_SPAN_US:
                raise ConfigError(
                    f"replay {path}: the trigger pulses lie at {lo}..{hi} us; a replay plays pulses "
                    f"within +-{MAX_TIME_US} us spanning at most 7 days"
                )
            if not (math.isfinite(self.rate_hz) and 0 < self.rate_hz <= 10_000):
                raise ConfigError(
                    f"replay {path}: the sync report's rate_hz {self.rate_hz!r} is not 0..10000 Hz"
                )
            margin = round(2e6 / self.rate_hz)  # the take window reaches one period past the pulses
            for fit in report.devices.values():
                check_clock_map(path, fit, lo - margin, hi + margin)
            self.config: dict[str, Any] = take.config
            self.sensors: dict[str, SensorTrack] = {}
            with open_checked(path, "r") as f:  # the structure check again: no file is trusted twice
                self.cameras = {name: self._camera(f, name, report) for name in take.cameras}
                for name in take.event_sensors:
                    sync = report.devices.get(name)
                    if sync is None:
                        raise ConfigError(f"replay {path}: event sensor {name} has no clock fit")
                    series = take.sensor(name)
                    trig, (w, h) = series.triggers, series.geometry
                    self.sensors[name] = SensorTrack(
                        name,
                        w,
                        h,
                        _clock_map(sync),
                        trig.t,
                        np.asarray(f[f"{trigger_in_group(name)}/{TriggerEdges.T_DEVICE}"][...], np.int64),
                        trig.p,
                        trig.channel,
                        series.count,
                    )

    @staticmethod
    def _camera(f: h5py.File, name: str, report: SyncReport) -> CameraTrack:
        g = f[frame_group(name)]
        n = int(g[Frames.IMAGES].shape[0])
        shape = tuple(int(v) for v in g[Frames.IMAGES].shape[1:])
        sync = report.devices.get(name)
        cmap = (
            None if sync is None else ClockMap(sync.device_ref_us, sync.rig_ref_us, sync.rate, sync.frac_us)
        )
        return CameraTrack(
            name,
            np.asarray(g[Frames.T_EXPOSURE_START][:n], np.int64),
            np.asarray(g[Frames.T_EXPOSURE_START_DEVICE][:n], np.int64),
            np.asarray(g[Frames.FRAME_COUNTER][:n], np.int64),
            np.asarray(g[Frames.EXPOSURE][:n], np.int64),
            shape,
            cmap,
            stored_pixel_format(g.attrs, shape, f"replay {f.filename}: /frames/{name}"),
        )

    def pulse_time(self, k: int) -> int | None:
        """Recorded box time of pulse k; a pulse the box log missed is put on the schedule."""
        if k > int(self.pulse_index[-1]):
            return None
        t = self._pulses.get(k)
        if t is None:
            return int(self.pulse_t[0]) + round((k - int(self.pulse_index[0])) * 1e6 / self.rate_hz)
        return int(t)

    def camera(self, name: str) -> CameraTrack:
        if name not in self.cameras:
            raise ConfigError(f"replay {self.path}: no camera {name!r} (cameras: {sorted(self.cameras)})")
        return self.cameras[name]

    def sensor(self, name: str) -> SensorTrack:
        if name not in self.sensors:
            raise ConfigError(
                f"replay {self.path}: no event sensor {name!r} (event sensors: {sorted(self.sensors)})"
            )
        return self.sensors[name]


class Timeline:
    """rig = true + shift, fixed when the replayed box is STARTed."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._shift: float | None = None

    def set(self, shift_us: float) -> None:
        with self._cond:
            self._shift = shift_us
            self._cond.notify_all()

    def wait(self, timeout_s: float) -> float | None:
        """The shift, waiting at most `timeout_s` wall seconds for the START."""
        with self._cond:
            self._cond.wait_for(lambda: self._shift is not None, timeout=timeout_s)
            return self._shift


def rig_to_device(cmap: ClockMap, rig_us: NDArray[np.int64]) -> tuple[NDArray[np.int64], int]:
    """Device times whose rig time through `cmap` is exactly `rig_us`; and how many have none
    (a rate above 1 skips a rig microsecond now and then: those get the nearest)."""
    d = cmap.to_device(rig_us)
    for _ in range(2):
        err = cmap.to_rig(d) - rig_us
        bad = err != 0
        if not bad.any():
            return d, 0
        d[bad] -= np.sign(err[bad])
    return d, int(np.count_nonzero(cmap.to_rig(d) != rig_us))


def clock_reset_param(spec: DeviceSpec) -> bool:
    reset = spec.int_param("clock_reset", 0)
    if reset not in (0, 1):
        raise ConfigError(f"device spec {spec.raw!r}: clock_reset={reset!r} (use 0 or 1)")
    return reset == 1


def reset_base(
    reset: bool, world: SimWorld, name: str, cmap: ClockMap | None, shift: float | None, now: float
) -> int:
    """`clock_reset=1`: a device opened after its replug counts from 0 again, so its recorded
    device times lose the device time of the replug instant; 0 otherwise."""
    fault = world.unplug_fault(name)
    if not reset or cmap is None or shift is None or not fault.replugged_before(now):
        return 0
    return int(cmap.to_device(np.array([round(fault.end_us + shift)], np.int64))[0])


# ---------------------------------------------------------------------------------------- world
def _take_path(spec: DeviceSpec) -> Path:
    raw = (spec.location + spec.path) if spec.location else spec.path
    path = Path(raw)
    if not path.is_absolute():
        raise ConfigError(f"device spec {spec.raw!r}: the take path must be absolute (replay:///abs/take.h5)")
    if not path.is_file():
        raise ConfigError(f"device spec {spec.raw!r}: no take file at {path}")
    return path


def replay_world(spec: DeviceSpec) -> tuple[SimWorld, Recording, Timeline]:
    """The world of a take's replay (one per take path and process), its recording and timeline."""
    path = _take_path(spec)
    world = get_world(f"replay:{path}", 0, spec.params.get("clock"))
    rec = world.resource("replay_recording", lambda: Recording(path))
    timeline = world.resource("replay_timeline", Timeline)
    assert isinstance(rec, Recording)
    assert isinstance(timeline, Timeline)
    return world, rec, timeline


def _device_name(spec: DeviceSpec) -> str:
    name = spec.params.get("device", "")
    if not name:
        raise ConfigError(f"device spec {spec.raw!r}: say which recorded device to replay (?device=NAME)")
    return name


# ---------------------------------------------------------------------------------------- trigger
class ReplayTriggerBox(SimTriggerBox):
    """The sim firmware, reporting the recorded pulse times instead of a computed schedule."""

    def _first_pulse_time(self) -> int:
        rec = self.world.resource("replay_recording", lambda: None)
        timeline = self.world.resource("replay_timeline", Timeline)
        assert isinstance(rec, Recording)
        assert isinstance(timeline, Timeline)
        t0 = rec.pulse_time(int(rec.pulse_index[0]))
        assert t0 is not None
        # The box clock is rig time: pulse 0 one start lead from now.
        self.clock = DeviceClock(t0 - (self.world.now_us() + START_LEAD_US), 0.0)
        self.world.register_clock("trigger", self.clock)
        timeline.set(self.clock.offset_us)
        self._recording = rec
        return t0

    def _pulse_box_time(self, t0: int, rate_hz: float, k: int) -> int | None:
        return self._recording.pulse_time(k + int(self._recording.pulse_index[0]))


def open_replay_trigger(spec: DeviceSpec) -> SerialTrigger:
    """Factory for `replay:///abs/take.h5?device=trigger` (+ the box's fault switches)."""
    check_params(spec, ReplayTriggerParams, "replayed trigger box")
    world, _, _ = replay_world(spec)
    return open_box_trigger(spec, world, ReplayTriggerBox)


# ---------------------------------------------------------------------------------------- camera
class ReplayCamera(Unpluggable, RgbCamera):
    """A recorded camera: frame j leaves when true time reaches its recorded exposure end."""

    _device_label = "camera"
    _capabilities = frozenset(
        {
            Capability.HARDWARE_TRIGGER,
            Capability.FRAME_COUNTER,
            Capability.DEVICE_TIMESTAMPS,
            Capability.EXPOSURE_CONTROL,
            Capability.COLOR,
        }
    )
    _overflow_name = "buffer_overflow"

    def __init__(
        self,
        spec: DeviceSpec,
        world: SimWorld,
        rec: Recording,
        timeline: Timeline,
        *,
        buffer_frames: int,
        drop_frames: frozenset[int],
        unplug: UnplugParams | None,
        clock_reset: bool = False,
        preload: int = 0,
    ) -> None:
        name = _device_name(spec)
        self._track = rec.camera(name)
        self._clock_reset, self._base = clock_reset, 0
        super().__init__(CameraSettings(), queue_len=buffer_frames, drain_on_stop=True)
        self._world, self._name, self._rec, self._timeline = world, name, rec, timeline
        self._drop_frames, self._unplug = drop_frames, unplug
        self._info = DeviceInfo(
            kind="rgb_camera",
            spec=spec.raw,
            vendor="rigd-replay",
            model="ReplayCamera",
            serial=f"{rec.path.name}/{name}",
            firmware="replay-1",
        )
        self._plug_in(world, name, spec.raw)
        self._lock = threading.Lock()
        self._file: h5py.File | None = None
        self._next = 0
        self._hold: Hold | None = None
        self._preload = min(preload, len(self._track.rig_us))
        self._images: NDArray[np.uint8] | None = None
        self._counts = {"transport_dropped": 0, "unplug_lost": 0}
        self._unlisten = self._fault.listen(self._on_unplug)

    @property
    def pixel_format(self) -> str:
        return self._track.pixel_format

    @property
    def frame_shape(self) -> tuple[int, ...]:
        return self._track.shape

    @property
    def frame_dtype(self) -> np.dtype[np.generic]:
        return np.dtype(np.uint8)

    def _do_configure(self, settings: CameraSettings) -> None:
        if settings.pixel_format and settings.pixel_format != self.pixel_format:
            raise ConfigError(
                f"replay camera {self._name}: recorded in {self.pixel_format}, settings ask "
                f"{settings.pixel_format}"
            )

    def _do_start(self) -> None:
        if self._file is None:
            self._file = open_checked(self._rec.path, "r")
        if self._preload and self._images is None:  # once: the frames a real driver hands over
            self._images = np.asarray(
                self._file[f"{frame_group(self._name)}/{Frames.IMAGES}"][: self._preload]
            )
        shift = self._timeline.wait(0.0)
        now = self._world.now_us()
        # A camera (re)started mid-replay goes on from the frames not yet due.
        due = 0 if shift is None else np.searchsorted(self._track.rig_us, now + shift, side="left")
        self._next = int(due)
        self._base = reset_base(self._clock_reset, self._world, self._name, self._track.cmap, shift, now)
        self._hold = self._world.hold() if self._world.virtual else None
        self._arm_unplug(self._unplug, now, lost_frames_on_edges=False)

    def _do_stop(self) -> None:
        pass

    def _do_close(self) -> None:
        self._unlisten()
        if self._hold is not None:
            self._hold.release()
        if self._file is not None:
            self._file.close()
            self._file = None

    def _counters(self) -> tuple[int, dict[str, int]]:
        with self._lock:
            counts = dict(self._counts)
        return counts["transport_dropped"] + counts["unplug_lost"], counts

    def _note_unplug_locked(self, lost: list[Any]) -> None:
        lost = [*lost, *self._queue.drain()]
        self._counts["unplug_lost"] += len(lost)
        if not self._unplug_noted:
            self._unplug_noted = True
            log.warning("replay camera %s unplugged; %d buffered frame(s) lost", self._name, len(lost))

    def _sleep_until(self, true_us: float) -> bool:
        if self._hold is not None:
            return self._hold.sleep_until(true_us, self._acq.stopping if self._acq else None)
        return self._world.sleep_until(true_us, self._acq.stopping if self._acq else None)

    def _grab(self, timeout_s: float) -> Frame | Signal | None:
        track = self._track
        if self._next >= len(track.rig_us):
            if self._hold is not None:
                self._hold.release()
            return END
        shift = self._timeline.wait(timeout_s)
        if shift is None:
            return None
        j = self._next
        leave = float(track.rig_us[j] + track.exposure_us[j]) - shift
        if not self._sleep_until(leave):
            return None  # stopped before this frame left the camera
        self._next = j + 1
        counter = int(track.counter[j])
        if counter in self._drop_frames:
            with self._lock:
                self._counts["transport_dropped"] += 1
            return None
        if self._dead(self._world.now_us()):
            with self._lock:
                self._counts["unplug_lost"] += 1
            if self._hold is not None:
                self._hold.release()  # a dead device no longer holds the world's time
            return END
        assert self._file is not None
        if self._images is not None:
            image = self._images[j % len(self._images)]
        else:
            image = np.asarray(self._file[f"{frame_group(self._name)}/{Frames.IMAGES}"][j])
        if self._hold is not None:
            wait_for_room(self._queue, _VIRTUAL_LEAD, lambda: self._stopping)
        return Frame(
            image=image,
            t_exposure_start_us=int(track.device_us[j]) - self._base,
            exposure_us=int(track.exposure_us[j]),
            frame_counter=counter,
            host_time_ns=time.monotonic_ns(),
            pixel_format=self._track.pixel_format,
        )


def open_replay_camera(spec: DeviceSpec) -> ReplayCamera:
    """Factory for `replay:///abs/take.h5?device=cam0[&buffer_frames=&drop_frames=&unplug_at_s=]`;
    `preload=N` holds the take's first N frames in memory and hands them out in turn (the
    recorded times and counters stay): a camera that costs the host what a driver handing
    over a buffer costs, not an HDF5 read, for benchmarks of the capture."""
    check_params(spec, ReplayCameraParams, f"replayed camera {spec.params.get('device', '?')}")
    world, rec, timeline = replay_world(spec)
    buffer_frames = _buffers(spec, "buffer_frames", 32)
    return ReplayCamera(
        spec,
        world,
        rec,
        timeline,
        buffer_frames=buffer_frames,
        drop_frames=frozenset(spec.int_list_param("drop_frames")),
        unplug=unplug_params(spec),
        clock_reset=clock_reset_param(spec),
        preload=spec.int_param("preload", 0),
    )


# ---------------------------------------------------------------------------------------- events
class ReplayEventSensor(Unpluggable, DecodingEventSensor[_Packet]):
    """A recorded event sensor: every `SLICE_US` of true time, the recorded events and trigger
    edges of that span, back in the sensor clock, as one EVT 3.0 buffer that the host decodes.
    A buffer the full queue gives up is counted as `packets_dropped`, its events in
    `device_dropped` and its trigger edges in `triggers_dropped` (as the sim sensor counts)."""

    _device_label = "event sensor"
    _capabilities = frozenset({Capability.TRIGGER_IN, Capability.DEVICE_TIMESTAMPS, Capability.CLOCK_SYNC})
    _overflow_name = "packets_dropped"
    _overflow_is_loss = False  # counted in events, by `_deliver`

    def __init__(
        self,
        spec: DeviceSpec,
        world: SimWorld,
        rec: Recording,
        timeline: Timeline,
        *,
        buffer_packets: int,
        unplug: UnplugParams | None,
        clock_reset: bool = False,
    ) -> None:
        name = _device_name(spec)
        self._track = rec.sensor(name)
        self._clock_reset, self._base = clock_reset, 0
        geometry = (self._track.width, self._track.height)
        super().__init__("evt3", geometry, buffers=buffer_packets, merge=64, drain_on_stop=True)
        self._world, self._name, self._rec, self._timeline = world, name, rec, timeline
        self._unplug = unplug
        self._info = DeviceInfo(
            kind="event_sensor",
            spec=spec.raw,
            vendor="rigd-replay",
            model="ReplayEventSensor",
            serial=f"{rec.path.name}/{name}",
            firmware="replay-1",
            facts={"evt_format": "evt3"},
        )
        self._plug_in(world, name, spec.raw)
        self._lock = threading.Lock()
        self._encoder = Evt3Encoder()
        self._take: Take | None = None
        self._buf = EventArray.empty()
        """Events read ahead (rig time), from `_pos` in the file: slices are cut from it, so a
        5 ms slice does not decompress whole chunks again."""
        self._pos = 0
        self._t_prev: float | None = None
        self._final = False
        self._hold: Hold | None = None
        self._counts = {
            "events": 0,
            "triggers": 0,
            "bytes": 0,
            "inexact_times": 0,
            "packets_lost_unplugged": 0,
            "triggers_dropped": 0,
        }
        self._events_lost = 0
        """Events of the buffers the full queue gave up (real time: the reader fell behind)."""
        self._unlisten = self._fault.listen(self._on_unplug)

    def warm_up(self) -> None:
        """Compile the EVT 3.0 encoder a slice runs, on a throwaway encoder and a tiny sample."""
        one = np.zeros(1, np.uint16)
        events = EventArray(one, one.copy(), np.ones(1, np.int8), np.ones(1, np.int64))
        Evt3Encoder().encode(
            events, TriggerEvents(np.zeros(1, np.int64), np.ones(1, np.uint8), np.zeros(1, np.uint8))
        )
        super().warm_up()

    def _do_start(self) -> None:
        if self._take is None:
            self._take = Take(self._rec.path)
        shift = self._timeline.wait(0.0)
        now = self._world.now_us()
        self._t_prev = None if shift is None else now
        self._buf = EventArray.empty()
        self._pos = 0 if shift is None else self._take.sensor(self._name).index(math.ceil(now + shift))
        self._base = reset_base(self._clock_reset, self._world, self._name, self._track.cmap, shift, now)
        self._final = False
        self._hold = self._world.hold() if self._world.virtual else None
        self._arm_unplug(self._unplug, self._world.now_us(), lost_frames_on_edges=False)

    def _do_close(self) -> None:
        self._unlisten()
        if self._hold is not None:
            self._hold.release()
        if self._take is not None:
            self._take.close()
            self._take = None
        super()._do_close()

    def _join(self, parts: list[_Packet]) -> tuple[bytes, int]:
        with self._lock:
            if self._dead(self._world.now_us()):
                self._note_unplug_locked(parts)
                raise self._unplugged_error()
        return super()._join(parts)

    def _counters(self) -> tuple[int, dict[str, int]]:
        with self._lock:
            counts, lost = dict(self._counts), self._events_lost
        _, decoder = super()._counters()
        return lost, {**counts, **decoder}

    def _deliver(self, item: _Packet) -> bool:
        """Into the queue; a full one gives up a buffer: its events and edges are counted."""
        lost = self._queue.put(item)
        if lost is None:
            return True
        with self._lock:
            self._events_lost += lost.n_events
            self._counts["triggers_dropped"] += lost.n_triggers
        log.warning(
            "replay event sensor %s: reader behind, queue full: dropped a buffer of %d events, %d triggers",
            self._name,
            lost.n_events,
            lost.n_triggers,
        )
        return False

    def _note_unplug_locked(self, lost: list[_Packet]) -> None:
        lost = [*lost, *self._queue.drain()]
        self._counts["packets_lost_unplugged"] += len(lost)
        if not self._unplug_noted:
            self._unplug_noted = True
            log.warning("replay event sensor %s unplugged", self._name)

    def _grab(self, timeout_s: float) -> _Packet | Signal | None:
        if self._final:
            if self._hold is not None:
                self._hold.release()
            return END
        shift = self._timeline.wait(timeout_s)
        if shift is None:
            return None
        if self._t_prev is None:  # the first slice reaches back to the start of the recording
            self._t_prev = -math.inf
            t_end = self._world.now_us()
        else:
            start = self._t_prev if math.isfinite(self._t_prev) else self._world.now_us()
            wake = start + SLICE_US
            stop = self._stop_asked
            awake = self._hold.sleep_until(wake, stop) if self._hold else self._world.sleep_until(wake, stop)
            now = self._world.now_us()
            if awake:
                t_end = start + SLICE_US * max(1, math.floor((now - start) / SLICE_US))
            else:
                t_end, self._final = now, True
        if self._dead(self._world.now_us()):
            with self._lock:
                self._note_unplug_locked([])
            if self._hold is not None:
                self._hold.release()  # a dead device no longer holds the world's time
            return END
        packet = self._slice(self._t_prev, t_end, shift)
        self._t_prev = t_end
        if packet is not None and self._hold is not None:
            wait_for_room(self._queue, _VIRTUAL_LEAD, self._stop_asked.is_set)
        return packet

    def _take_until(self, hi_rig: int) -> EventArray:
        """The recorded events before rig time `hi_rig` not handed out yet, read ahead in blocks."""
        assert self._take is not None
        n = self._track.n_events
        while self._pos < n and (len(self._buf) == 0 or int(self._buf.t[-1]) < hi_rig):
            stop = min(self._pos + _READ_AHEAD, n)
            block = self._take.sensor(self._name).by_index(self._pos, stop)
            self._buf = EventArray.concatenate([self._buf, block])
            self._pos = stop
        k = int(np.searchsorted(self._buf.t, hi_rig, side="left"))
        out, self._buf = self._buf[:k], self._buf[k:]
        return out

    def _slice(self, t0: float, t1: float, shift: float) -> _Packet | None:
        """The recorded data of true time [t0, t1), in the sensor clock, encoded."""
        assert self._take is not None
        track = self._track
        lo_rig = None if math.isinf(t0) else math.ceil(t0 + shift)
        hi_rig = math.ceil(t1 + shift)
        ev = self._take_until(hi_rig)
        t_dev, inexact = rig_to_device(track.cmap, ev.t)
        a = 0 if lo_rig is None else int(np.searchsorted(track.trig_rig, lo_rig, side="left"))
        b = int(np.searchsorted(track.trig_rig, hi_rig, side="left"))
        t_dev -= self._base
        trig = TriggerEvents(track.trig_device[a:b] - self._base, track.trig_p[a:b], track.trig_channel[a:b])
        n = len(ev)
        events = ev.with_time(t_dev)
        # Time words up to the slice end: the host knows how far the stream got, events or not.
        end_device, _ = rig_to_device(track.cmap, np.array([hi_rig - 1], np.int64))
        payload = self._encoder.encode(events, trig) + self._encoder.mark_time(
            int(end_device[0]) - self._base
        )
        with self._lock:
            self._counts["events"] += n
            self._counts["triggers"] += b - a
            self._counts["bytes"] += len(payload)
            self._counts["inexact_times"] += inexact
        return _Packet(
            payload,
            time.monotonic_ns(),
            n,
            b - a,
            int(t_dev[0]) if n else 0,
            int(t_dev[-1]) if n else 0,
            t1,
        )


def _buffers(spec: DeviceSpec, name: str, default: int) -> int:
    """A replayed device's buffer size parameter: at least one."""
    n = spec.int_param(name, default)
    if n < 1:
        raise ConfigError(f"device spec {spec.raw!r}: {name}={n} must be >= 1")
    return n


def open_replay_event_sensor(spec: DeviceSpec) -> ReplayEventSensor:
    """Factory for `replay:///abs/take.h5?device=ev0[&buffer_packets=&unplug_at_s=]`."""
    check_params(spec, ReplaySensorParams, f"replayed event sensor {spec.params.get('device', '?')}")
    world, rec, timeline = replay_world(spec)
    buffer_packets = _buffers(spec, "buffer_packets", 1024)
    return ReplayEventSensor(
        spec,
        world,
        rec,
        timeline,
        buffer_packets=buffer_packets,
        unplug=unplug_params(spec),
        clock_reset=clock_reset_param(spec),
    )


def replay_spec(take: Path, device: str, **params: str) -> str:
    """The spec that replays one device of a take."""
    query = "&".join(f"{k}={v}" for k, v in {"device": device, **params}.items())
    return f"{SCHEME}://{take.resolve()}?{query}"


__all__ = [
    "DeviceError",
    "Recording",
    "open_replay_camera",
    "open_replay_event_sensor",
    "open_replay_trigger",
    "replay_spec",
    "rig_to_device",
]
