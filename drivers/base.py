"""One abstract interface per device kind, with explicit capabilities and one lifecycle.

The daemon talks only to these classes; which backend sits behind one is decided by the
device spec (see `drivers.registry`). The public methods are concrete here and enforce the
state machine (open -> configure* -> start -> stop -> ... -> close), so a backend writes only
small hooks: `_do_configure`, `_do_start`, `_do_stop`, `_do_close`, and `_grab`, which the
acquisition thread the base owns calls (`drivers.lifecycle`), or `_read`, which runs on the
reader's thread (a file replay), or both (a streaming event sensor grabs device buffers and
decodes them as they are read: `drivers.evt_stream.DecodingEventSensor`). Every backend,
simulated or real, runs the contract suites in `drivers.testing`.
"""

from __future__ import annotations

import abc
import enum
import logging
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from types import TracebackType
from typing import ClassVar, Generic, Self, cast

import numpy as np
from pydantic import BaseModel
from typing_extensions import TypeVar  # a type parameter's default (PEP 696) before 3.13

from drivers.lifecycle import Acquisition, DeliveryQueue, Drop, Signal
from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.errors import ConfigError, DeviceError
from rigd.core.events import EventPacket
from rigd.core.frames import Frame
from rigd.core.host_clock import MONOTONIC, HostClock
from rigd.core.kinds import DeviceKind
from rigd.core.settings import CameraSettings, EventSensorSettings, TriggerSettings

log = logging.getLogger(__name__)


class Capability(enum.StrEnum):
    """What a device can do. Each flag is a promise the contract suites check; the capture
    preflight compares `required_capabilities(settings)` with these instead of guessing from
    the backend, and configure() refuses settings that need a flag the device lacks."""

    HARDWARE_TRIGGER = "hardware_trigger"
    """Camera exposes exactly one frame per rising edge on its trigger input, none without."""
    FREE_RUN = "free_run"
    """Camera can run on its own clock, without pulses (`trigger_mode = "free_run"`)."""
    SOFTWARE_SYNC = "software_sync"
    """Camera has no trigger input: its frames are matched to pulses by host time, so their
    rig times are only as good as the host's reception latency. Never with HARDWARE_TRIGGER."""
    FRAME_COUNTER = "frame_counter"
    """Frames carry a device counter, so transport losses show as gaps."""
    DEVICE_TIMESTAMPS = "device_timestamps"
    """Data carry timestamps from the device's own clock (not the host's)."""
    EXPOSURE_CONTROL = "exposure_control"
    """Camera applies `exposure_us` (within its bounds); without it the exposure is its own."""
    COLOR = "color"
    """Camera can deliver colour frames (`pixel_format = "rgb8"`; `"bayer_rg8"` needs the
    backend to offer the raw mosaic too, which its configure() checks)."""
    TRIGGER_IN = "trigger_in"
    """Event sensor delivers the rig's trigger edges as trigger events in its own clock."""
    CLOCK_SYNC = "clock_sync"
    """Event sensor can share its clock with another over a sync cable (`sync_mode`)."""
    PULSE_TIMESTAMPS = "pulse_timestamps"
    """Trigger source reports the time of every pulse it emitted (the rig timebase)."""
    PULSE_COUNT = "pulse_count"
    """Trigger source emits an exact number of pulses and stops by itself (`start(n)`)."""


#: Why a setting needs a capability: the second half of configure()'s refusal.
_WHY: dict[Capability, str] = {
    Capability.HARDWARE_TRIGGER: "trigger_mode 'hardware' needs a trigger input "
    "(use 'free_run': frames are then matched to pulses by host time)",
    Capability.FREE_RUN: "trigger_mode 'free_run' needs a camera that runs on its own clock",
    Capability.EXPOSURE_CONTROL: "an exposure_us other than the default needs a settable exposure",
    Capability.COLOR: "pixel_format 'rgb8' or 'bayer_rg8' needs a color camera",
    Capability.TRIGGER_IN: "enable_trigger_in needs trigger edges from the sensor "
    "(set enable_trigger_in = false)",
    Capability.CLOCK_SYNC: "sync_mode master/slave needs a sensor with a sync cable input",
    Capability.PULSE_TIMESTAMPS: "the rig timebase needs the time of every pulse",
    Capability.PULSE_COUNT: "start(n_pulses) needs a trigger that stops by itself",
}
_DEFAULT_EXPOSURE_US = CameraSettings().exposure_us


def missing_capabilities(device: Device, wanted: Iterable[Capability]) -> frozenset[Capability]:
    """The wanted capabilities the device lacks (empty when it can do them all)."""
    return frozenset(wanted) - device.capabilities


def explain_missing(missing: Iterable[Capability]) -> str:
    """Each missing capability and why the settings need it, in one line."""
    return "; ".join(f"{c}: {_WHY[c]}" for c in sorted(missing))


def check_capabilities(device: Device, wanted: Iterable[Capability]) -> None:
    """Raise ConfigError naming the device, each missing capability and why it is needed."""
    missing = missing_capabilities(device, wanted)
    if missing:
        raise ConfigError(f"{device.label} cannot do what its settings ask: {explain_missing(missing)}")


@dataclass(slots=True)
class AcquisitionStats:
    """Counters a device keeps about what it delivered and what it lost."""

    delivered: int = 0
    device_dropped: int = 0
    """Lost inside the device or its transport (buffer overrun, incomplete buffers)."""
    extra: dict[str, int] = field(default_factory=dict)


_NOUNS: dict[DeviceKind, str] = {"rgb_camera": "camera", "event_sensor": "event sensor", "trigger": "trigger"}


class Device(abc.ABC):
    """What every device shares: identity, capabilities, and a close that stops it first.

    Backends set `_info` and `_capabilities` (or override the properties when they change),
    and `_label` when messages should name the device otherwise than by kind and spec.
    """

    kind: ClassVar[DeviceKind]
    _info: DeviceInfo
    _capabilities: frozenset[Capability] = frozenset()
    _label: str = ""
    host_clock: HostClock = MONOTONIC
    """What this device stamps `host_time_ns` with (`rigd.core.host_clock`): a capture compares
    its items' host times with "now" on this clock. A simulated world sets its own."""

    def __init__(self) -> None:
        self._closed = False
        # Serializes start/stop/configure/close; readers never take it.
        self._state_lock = threading.RLock()

    @property
    def info(self) -> DeviceInfo:
        return self._info

    @property
    def capabilities(self) -> frozenset[Capability]:
        return self._capabilities

    @property
    def label(self) -> str:
        """How messages name this device."""
        if self._label:
            return self._label
        try:
            spec = self.info.spec
        except AttributeError:  # asked while opening, before the backend knew its identity
            spec = type(self).__name__
        return f"{_NOUNS[self.kind]} {spec}"

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Stop the device if it runs, then release it. Idempotent."""
        with self._state_lock:
            if self._closed:
                return
            try:
                self._stop_for_close()
            finally:
                self._closed = True
                self._do_close()

    def warm_up(self) -> None:  # noqa: B027 - optional hook, most devices compile nothing
        """Compile what acquiring will run (numba kernels: EVT codecs, simulator pixels) before
        the take starts. On a cold JIT cache that takes seconds, and a device that spends them
        on its first packets falls behind its data; the capture preflight calls this once per
        device while the trigger is still off (`rigd.app.capture.preflight.warm_up`)."""

    def _check_open(self) -> None:
        """DeviceError naming the device when it is closed or gone."""
        if self._closed:
            raise DeviceError(f"{self.label} is closed")
        self._check_present()

    def _check_present(self) -> None:  # noqa: B027 - optional hook, nothing to check by default
        """Hook: raise DeviceError when the device is gone (unplugged) though not closed."""

    @abc.abstractmethod
    def _stop_for_close(self) -> None:
        """What close() does before releasing: stop acquiring (or pulsing)."""

    def _do_close(self) -> None:  # noqa: B027 - optional hook, nothing to release by default
        """Hook: release the device (ports, handles, threads of its own)."""

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


T = TypeVar("T")
S = TypeVar("S", bound=BaseModel)
G = TypeVar("G", default=T)
"""What `_grab` returns and the queue holds: by default what reads return."""
E = TypeVar("E", default=EventPacket)
"""What an event sensor's `_grab` returns: a packet, or a device buffer its reads decode."""


class AcquiringDevice(Device, Generic[T, S, G]):
    """Lifecycle of a device that acquires between start and stop (cameras, event sensors).

    A grabbing backend passes `queue_len` and implements `_grab(timeout_s)`: the base runs it
    on an acquisition thread from start to stop, keeps what it returns in a bounded queue
    (overflow counted under `_overflow_name`) and keeps the exception that ends it for the
    next read. Reads hand out one queued item each, unless the backend's `_read` takes several
    at a time (`_read_queued`) and turns them into one (the grabbed type `G` differs from `T`
    then: a streaming event sensor decodes buffers). Any other backend implements
    `_read(timeout_s)` alone.
    """

    _overflow_name: ClassVar[str] = "host_queue_dropped"
    #: Whether `stats().device_dropped` includes the queue's overflow; False where the backend
    #: counts what an overflow lost in its own `_counters` (a simulated sensor: its events).
    _overflow_is_loss: ClassVar[bool] = True

    def __init__(
        self,
        settings: S,
        *,
        queue_len: int | None = None,
        drop: Drop = "newest",
        drain_on_stop: bool = False,
        join_timeout_s: float | None = None,
    ) -> None:
        super().__init__()
        self._settings = settings
        self._running = False
        self._count_lock = threading.Lock()
        self._delivered = 0
        self._acq: Acquisition[G] | None = None
        if queue_len is not None:
            self._acq = Acquisition(
                type(self).__name__,
                self._grab,
                DeliveryQueue(queue_len, drop),
                deliver=self._deliver,
                drain_on_stop=drain_on_stop,
                join_timeout_s=join_timeout_s,
            )

    # -- public lifecycle ------------------------------------------------------------------
    @property
    def acquiring(self) -> bool:
        """True between start() and stop()."""
        return self._running

    @abc.abstractmethod
    def required_capabilities(self, settings: S) -> frozenset[Capability]: ...

    def configure(self, settings: S) -> None:
        """Apply settings; only while open and stopped. ConfigError if the device cannot."""
        with self._state_lock:
            self._check_open()
            if self._running:
                raise DeviceError(f"{self.label}: configure while started; stop it first")
            check_capabilities(self, self.required_capabilities(settings))
            self._do_configure(settings)
            self._settings = settings.model_copy()

    def start(self) -> None:
        """Start acquiring; DeviceError naming the device when it is closed or started."""
        with self._state_lock:
            self._check_open()
            if self._running:
                raise DeviceError(f"{self.label} is already started")
            if self._acq is not None and self._acq.alive:
                raise DeviceError(f"{self.label}: the last acquisition has not ended yet; try again")
            self._do_start()
            self._running = True
            if self._acq is not None:
                self._acq.label = self.label
                self._acq.start()
        log.info("%s started", self.label)

    def stop(self) -> None:
        """Stop acquiring; what was acquired stays readable. Idempotent."""
        with self._state_lock:
            if not self._running:
                return
            self._running = False
            try:
                self._do_stop()
            finally:
                if self._acq is not None:
                    self._acq.stop()
        if log.isEnabledFor(logging.INFO):
            log.info("%s stopped; %s", self.label, self.stats())

    def stats(self) -> AcquisitionStats:
        dropped, extra = self._counters()
        if self._acq is not None:
            overflow = self._acq.queue.dropped
            extra[self._overflow_name] = overflow
            if self._overflow_is_loss:
                dropped += overflow
        with self._count_lock:
            delivered = self._delivered
        return AcquisitionStats(delivered=delivered, device_dropped=dropped, extra=extra)

    def _stop_for_close(self) -> None:
        self.stop()

    def _read_next(self, timeout_s: float) -> T | None:
        self._check_open()
        item = self._read(timeout_s)
        if item is not None:
            n = self._size(item)
            with self._count_lock:
                self._delivered += n
        return item

    @property
    def _queue(self) -> DeliveryQueue[G]:
        """The bounded queue between the acquisition thread and the readers."""
        return self._acquisition.queue

    @property
    def _stopping(self) -> bool:
        """On the acquisition thread: stop() was asked (a draining grab finishes up)."""
        return self._acq is not None and self._acq.stopping.is_set()

    @property
    def _stop_asked(self) -> threading.Event:
        """On the acquisition thread: set once stop() was asked, for a grab to wait on."""
        return self._acquisition.stopping

    @property
    def _acquisition(self) -> Acquisition[G]:
        if self._acq is None:
            raise NotImplementedError(f"{type(self).__name__} has no acquisition thread")
        return self._acq

    def _read_queued(self, timeout_s: float, max_items: int = 1) -> list[G]:
        """Reader's thread: up to `max_items` queued items, oldest first, waiting at most
        `timeout_s` for the first; once the queue is empty, the error that ended the
        acquisition thread, as DeviceError."""
        return self._acquisition.read(timeout_s, max_items=max_items)

    # -- hooks -----------------------------------------------------------------------------
    def _do_configure(self, settings: S) -> None:
        """Apply settings to the device (the base keeps them in `_settings` after)."""

    def _do_start(self) -> None:
        """Make the device produce; the acquisition thread starts right after."""

    def _do_stop(self) -> None:
        """Make the device stop producing; the acquisition thread is joined right after."""

    def _grab(self, timeout_s: float) -> G | Signal | None:
        """Acquisition thread: the next item, None when none came within the timeout, END
        when the device has nothing more. Exceptions end the thread and reach the reader."""
        raise NotImplementedError(f"{type(self).__name__} has no acquisition thread")

    def _read(self, timeout_s: float) -> T | None:
        """Reader's thread: the next item or None. By default: the next grabbed item (a backend
        whose grabbed items are not what it reads (`G`) turns them into one here)."""
        if self._acq is None:
            raise NotImplementedError(f"{type(self).__name__} implements neither _grab nor _read")
        items = self._read_queued(timeout_s)
        return cast(T, items[0]) if items else None

    def _deliver(self, item: G) -> bool:
        """Acquisition thread: queue an item; False when the full queue lost one (counted)."""
        if self._queue.put(item) is None:
            return True
        n = self._queue.dropped
        if n == 1 or n % 100 == 0:
            log.warning("%s: reader is behind, queue full: %d item(s) dropped so far", self.label, n)
        return False

    def _counters(self) -> tuple[int, dict[str, int]]:
        """Backend counters: (items lost in the device or its transport, named extras)."""
        return 0, {}

    @abc.abstractmethod
    def _size(self, item: T) -> int:
        """How much of what `stats().delivered` counts an item holds."""


class RgbCamera(AcquiringDevice[Frame, CameraSettings]):
    """A frame camera. In hardware-trigger mode it exposes one frame per pulse."""

    kind = "rgb_camera"

    @property
    @abc.abstractmethod
    def frame_shape(self) -> tuple[int, ...]:
        """(H, W) or (H, W, C) of the frames `read_frame` returns under the current settings."""

    @property
    @abc.abstractmethod
    def frame_dtype(self) -> np.dtype[np.generic]: ...

    @property
    def pixel_format(self) -> str:
        """What the frames hold under the current settings (rigd.core.pixels.PIXEL_FORMATS): the
        configured format, else mono8 or rgb8 by the frame shape. Backends whose default can be
        a Bayer mosaic override it, since an (H, W) mosaic looks like mono8."""
        return self._settings.pixel_format or ("rgb8" if len(self.frame_shape) == 3 else "mono8")

    def required_capabilities(self, settings: CameraSettings) -> frozenset[Capability]:
        """Hardware mode needs HARDWARE_TRIGGER, free-run FREE_RUN; a non-default exposure
        needs EXPOSURE_CONTROL and colour frames (rgb8, bayer_rg8) COLOR."""
        needs = {Capability.HARDWARE_TRIGGER if settings.trigger_mode == "hardware" else Capability.FREE_RUN}
        if settings.exposure_us != _DEFAULT_EXPOSURE_US:
            needs.add(Capability.EXPOSURE_CONTROL)
        if settings.pixel_format in ("rgb8", "bayer_rg8"):
            needs.add(Capability.COLOR)
        return frozenset(needs)

    def read_frame(self, timeout_s: float) -> Frame | None:
        """Next frame in delivery order, or None when none arrives before the timeout."""
        return self._read_next(timeout_s)

    def _size(self, item: Frame) -> int:
        return 1


class EventSensor(AcquiringDevice[EventPacket, EventSensorSettings, E]):
    """An event camera delivering change events and trigger-in edges. A streaming sensor's
    acquisition thread grabs device buffers (`E`) that its reads decode into packets
    (`drivers.evt_stream.DecodingEventSensor`)."""

    kind = "event_sensor"
    #: Its packets carry the EVT words they were decoded from (`EventPacket.raw`, in the format
    #: `evt_format` names), so a take can store them as sent; False: decoded events only.
    delivers_evt_words: bool = False

    @property
    def evt_format(self) -> str | None:
        """The EVT format of the words its packets carry (None: decoded events only)."""
        return None

    @property
    @abc.abstractmethod
    def geometry(self) -> tuple[int, int]:
        """(width, height) in pixels."""

    def required_capabilities(self, settings: EventSensorSettings) -> frozenset[Capability]:
        """Trigger-in needs TRIGGER_IN; a master or slave sync mode needs CLOCK_SYNC."""
        needs = set()
        if settings.enable_trigger_in:
            needs.add(Capability.TRIGGER_IN)
        if settings.sync_mode != "standalone":
            needs.add(Capability.CLOCK_SYNC)
        return frozenset(needs)

    def read_events(self, timeout_s: float) -> EventPacket | None:
        """Next packet; event and trigger times never decrease across packets."""
        return self._read_next(timeout_s)

    @property
    def stream_time_us(self) -> int | None:
        """Sensor time up to which everything has been read, events or not (a stream's time
        words tell it); None where the device does not say. Lets a reader know a quiet sensor
        has got past a time although no event came."""
        return None

    def _size(self, item: EventPacket) -> int:
        return item.n_events


class Trigger(Device):
    """The rig's global trigger source. Its clock is the rig timebase.

    Whether it runs is the source's to say (a counted run ends by itself), so the base tracks
    only open/closed: every call on a closed trigger raises DeviceError naming it, and close()
    sends a best-effort stop first, since a trigger left pulsing keeps the rig exposing.
    """

    kind = "trigger"
    follows: ClassVar[bool] = False
    """A trigger that follows a box another host drives (a multi-host rig's follower): its stop
    only learns how many pulses the box emitted, and the take's last pulse is that box's."""

    def __init__(self) -> None:
        super().__init__()
        self._settings = TriggerSettings()

    def required_capabilities(
        self, settings: TriggerSettings, n_pulses: int | None = None
    ) -> frozenset[Capability]:
        """Always PULSE_TIMESTAMPS (the rig timebase); PULSE_COUNT for a counted run."""
        needs = {Capability.PULSE_TIMESTAMPS}
        if n_pulses is not None:
            needs.add(Capability.PULSE_COUNT)
        return frozenset(needs)

    def configure(self, settings: TriggerSettings) -> None:
        """Apply rate and pulse width; ConfigError when the pulse does not fit the period."""
        self._check_open()
        period_us = 1e6 / settings.rate_hz
        if settings.pulse_width_us >= period_us:
            raise ConfigError(
                f"{self.label}: pulse width {settings.pulse_width_us} us must be shorter "
                f"than the period {period_us:.1f} us at {settings.rate_hz:g} Hz"
            )
        check_capabilities(self, self.required_capabilities(settings))
        self._do_configure(settings)
        self._settings = settings.model_copy()

    def arm(self) -> None:
        """Reset the pulse counter and get ready; no pulses yet."""
        self._check_open()
        self._do_arm()

    def start(self, n_pulses: int | None = None) -> int:
        """Begin pulsing (forever, or exactly `n_pulses`); returns the start time in rig us."""
        self._check_open()
        if n_pulses is not None:
            if n_pulses < 1:
                raise ConfigError(f"{self.label}: n_pulses must be >= 1, got {n_pulses}")
            check_capabilities(self, {Capability.PULSE_COUNT})
        return self._do_start(n_pulses)

    def stop(self) -> int:
        """Stop pulsing; returns the number of pulses emitted since START."""
        self._check_open()
        return self._do_stop()

    def is_running(self) -> bool:
        self._check_open()
        return self._is_running()

    def read_pulses(self, timeout_s: float) -> PulseBatch:
        """Pulse records received since the last call (maybe empty after the timeout)."""
        self._check_open()
        return self._read_pulses(timeout_s)

    def pulse_count(self) -> int:
        """Pulses emitted since START, as the trigger source counts them."""
        self._check_open()
        return self._pulse_count()

    def clock_us(self) -> int:
        """The trigger source's clock now (rig time)."""
        self._check_open()
        return self._clock_us()

    def link_stats(self) -> dict[str, int]:
        """Counters of the link to the trigger source (corrupt lines, retries, recovered
        pulses); written into the take so a noisy cable is visible afterwards."""
        return {}

    def link_lost(self) -> str | None:
        """Why the pulse records can no longer come (a multi-host follower that lost its
        coordinator), or None: the take then stops cleanly, keeping what it has, naming it."""
        return None

    def diag(self) -> dict[str, int]:
        """The box's own counters (records it could not send live, input it lost, edges it
        armed late), asked of the box; empty for a trigger that keeps none."""
        return {}

    def _stop_for_close(self) -> None:
        try:
            self._do_stop()
        except DeviceError as exc:
            log.warning("%s: stop on close failed: %s", self.label, exc)

    # -- hooks -----------------------------------------------------------------------------
    @abc.abstractmethod
    def _do_configure(self, settings: TriggerSettings) -> None: ...

    @abc.abstractmethod
    def _do_arm(self) -> None: ...

    @abc.abstractmethod
    def _do_start(self, n_pulses: int | None) -> int: ...

    @abc.abstractmethod
    def _do_stop(self) -> int: ...

    @abc.abstractmethod
    def _is_running(self) -> bool: ...

    @abc.abstractmethod
    def _read_pulses(self, timeout_s: float) -> PulseBatch: ...

    @abc.abstractmethod
    def _pulse_count(self) -> int: ...

    @abc.abstractmethod
    def _clock_us(self) -> int: ...
