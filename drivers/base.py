"""One abstract interface per device kind, with explicit capabilities.

The daemon talks only to these classes; which backend sits behind one is decided by the
device spec (see `drivers.registry`). Every backend, simulated or real, must pass the
contract suites in `tests/contracts/`.
"""

from __future__ import annotations

import abc
import enum
from dataclasses import dataclass, field
from types import TracebackType
from typing import ClassVar, Self

import numpy as np

from rigd.core.devices import DeviceInfo, DeviceKind, PulseBatch
from rigd.core.events import EventArray, TriggerEvents
from rigd.core.frames import Frame
from rigd.core.settings import CameraSettings, EventSensorSettings, TriggerSettings


class Capability(enum.StrEnum):
    """What a device can do; the daemon checks these instead of guessing from the backend."""

    HARDWARE_TRIGGER = "hardware_trigger"
    """Camera exposes one frame per trigger pulse."""
    FREE_RUN = "free_run"
    """Camera can run on its own clock, without pulses."""
    FRAME_COUNTER = "frame_counter"
    """Frames carry a device counter, so transport losses show as gaps."""
    DEVICE_TIMESTAMPS = "device_timestamps"
    """Data carry timestamps from the device's own clock."""
    EXPOSURE_CONTROL = "exposure_control"
    COLOR = "color"
    TRIGGER_IN = "trigger_in"
    """Event sensor latches external trigger edges as trigger events."""
    PULSE_TIMESTAMPS = "pulse_timestamps"
    """Trigger source reports the time of every pulse it emitted."""
    PULSE_COUNT = "pulse_count"
    """Trigger source emits an exact number of pulses and stops by itself."""


@dataclass(slots=True)
class AcquisitionStats:
    """Counters a device keeps about what it delivered and what it lost."""

    delivered: int = 0
    device_dropped: int = 0
    """Lost inside the device or its transport (buffer overrun, incomplete buffers)."""
    extra: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class EventPacket:
    """Events and trigger edges read in one call, both in the sensor's clock."""

    events: EventArray
    triggers: TriggerEvents
    host_time_ns: int


class Device(abc.ABC):
    """Lifecycle shared by every device: open in the constructor or `open`, close once."""

    kind: ClassVar[DeviceKind]

    @property
    @abc.abstractmethod
    def info(self) -> DeviceInfo: ...

    @property
    @abc.abstractmethod
    def capabilities(self) -> frozenset[Capability]: ...

    @abc.abstractmethod
    def close(self) -> None:
        """Release the device. Idempotent."""

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


class RgbCamera(Device):
    """A frame camera. In hardware-trigger mode it exposes one frame per pulse."""

    kind = "rgb_camera"

    @property
    @abc.abstractmethod
    def frame_shape(self) -> tuple[int, ...]:
        """(H, W) or (H, W, C) of the frames `read_frame` returns under the current settings."""

    @property
    @abc.abstractmethod
    def frame_dtype(self) -> np.dtype[np.generic]: ...

    @abc.abstractmethod
    def configure(self, settings: CameraSettings) -> None:
        """Apply settings; only allowed while stopped. Raises ConfigError if unsupported."""

    @abc.abstractmethod
    def start(self) -> None:
        """Start acquisition: from now on frames are exposed on every pulse (or free-run)."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop acquiring. Frames already buffered stay readable."""

    @abc.abstractmethod
    def read_frame(self, timeout_s: float) -> Frame | None:
        """Next frame in delivery order, or None when none arrives before the timeout."""

    @abc.abstractmethod
    def stats(self) -> AcquisitionStats: ...


class EventSensor(Device):
    """An event camera delivering change events and trigger-in edges."""

    kind = "event_sensor"

    @property
    @abc.abstractmethod
    def geometry(self) -> tuple[int, int]:
        """(width, height) in pixels."""

    @abc.abstractmethod
    def configure(self, settings: EventSensorSettings) -> None: ...

    @abc.abstractmethod
    def start(self) -> None: ...

    @abc.abstractmethod
    def stop(self) -> None: ...

    @abc.abstractmethod
    def read_events(self, timeout_s: float) -> EventPacket | None:
        """Next packet; event and trigger times never decrease across packets."""

    @abc.abstractmethod
    def stats(self) -> AcquisitionStats: ...


class Trigger(Device):
    """The rig's global trigger source. Its clock is the rig timebase."""

    kind = "trigger"

    @abc.abstractmethod
    def configure(self, settings: TriggerSettings) -> None: ...

    @abc.abstractmethod
    def arm(self) -> None:
        """Reset the pulse counter and get ready; no pulses yet."""

    @abc.abstractmethod
    def start(self, n_pulses: int | None = None) -> int:
        """Begin pulsing (forever, or exactly `n_pulses`); returns the start time in rig us."""

    @abc.abstractmethod
    def stop(self) -> int:
        """Stop pulsing; returns the number of pulses emitted since START."""

    @abc.abstractmethod
    def is_running(self) -> bool: ...

    @abc.abstractmethod
    def read_pulses(self, timeout_s: float) -> PulseBatch:
        """Pulse records received since the last call (maybe empty after the timeout)."""

    @abc.abstractmethod
    def pulse_count(self) -> int:
        """Pulses emitted since START, as the trigger source counts them."""

    @abc.abstractmethod
    def clock_us(self) -> int:
        """The trigger source's clock now (rig time)."""

    def link_stats(self) -> dict[str, int]:
        """Counters of the link to the trigger source (corrupt lines, retries, recovered
        pulses); written into the take so a noisy cable is visible afterwards."""
        return {}
