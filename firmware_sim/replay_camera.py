"""A recorded camera played back (`replay:///abs/TAKE.h5?device=CAM`): each recorded frame, with its
device timestamp and counters, leaves when true time reaches its recorded exposure end.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray

from drivers.base import Capability, RgbCamera
from drivers.lifecycle import END, Signal
from drivers.registry import DeviceSpec
from firmware_sim.clock import Hold
from firmware_sim.replay_recording import (
    VIRTUAL_LEAD,
    Recording,
    Timeline,
    buffers_param,
    clock_reset_param,
    device_name,
    replay_world,
    reset_base,
)
from firmware_sim.spec_params import ReplayCameraParams, check_params
from firmware_sim.world import SimWorld, Unpluggable, UnplugParams, unplug_params, wait_for_room
from rigd.core.devices import DeviceInfo
from rigd.core.errors import ConfigError
from rigd.core.frames import Frame
from rigd.core.layout import Frames, frame_group
from rigd.core.settings import CameraSettings
from rigd.take.h5file import open_checked

log = logging.getLogger(__name__)


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
        name = device_name(spec)
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
            wait_for_room(self._queue, VIRTUAL_LEAD, lambda: self._stopping)
        return Frame(
            image=image,
            t_exposure_start_us=int(track.device_us[j]) - self._base,
            exposure_us=int(track.exposure_us[j]),
            frame_counter=counter,
            host_time_ns=self.host_clock.now_ns(),
            pixel_format=self._track.pixel_format,
        )


def open_replay_camera(spec: DeviceSpec) -> ReplayCamera:
    """Factory for `replay:///abs/take.h5?device=cam0[&buffer_frames=&drop_frames=&unplug_at_s=]`;
    `preload=N` holds the take's first N frames in memory and hands them out in turn (the
    recorded times and counters stay): a camera that costs the host what a driver handing
    over a buffer costs, not an HDF5 read, for benchmarks of the capture."""
    check_params(spec, ReplayCameraParams, f"replayed camera {spec.params.get('device', '?')}")
    world, rec, timeline = replay_world(spec)
    buffer_frames = buffers_param(spec, "buffer_frames", 32)
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
