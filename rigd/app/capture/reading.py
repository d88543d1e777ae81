"""The reading part of a device channel, one class per device kind: how the device is opened,
configured, read and entered in the take, and what its items say about time.

The channel (`channel.DeviceChannel`) runs the same loop for every kind: read, re-tie a
restarted clock, pass the window gate, shed under overload, queue for the writer. Everything in
that loop that depends on what the device is (a camera's frames, an event sensor's packets) is
asked of this part, which the factory (`kinds`) chose once; the loop never tests a kind
(decision 0028).
"""

from __future__ import annotations

import dataclasses
import math
import threading
from abc import ABC, abstractmethod
from typing import Any, ClassVar, Generic, TypeVar

from drivers.base import Capability, EventSensor, RgbCamera
from drivers.registry import open_device
from rigd.app.capture.gate import EventGate, FrameGate, GateMode, WindowGate
from rigd.app.capture.items import EventsItem, FrameItem
from rigd.app.capture.live import HostAnchors
from rigd.app.capture.streams import DeviceStream
from rigd.app.capture.window import TakeWindow
from rigd.core.devices import SensorKind
from rigd.core.events import EventArray, EventPacket
from rigd.core.frames import Frame
from rigd.core.schema import LossKind
from rigd.core.settings import CameraSettings, EventSensorSettings
from rigd.take.writer import TakeWriter

DevT = TypeVar("DevT", RgbCamera, EventSensor)
ItemT = TypeVar("ItemT", Frame, EventPacket)


class Reading(ABC, Generic[DevT, ItemT]):
    """One device kind's side of the acquisition loop (its settings are the config entry's)."""

    kind: ClassVar[SensorKind]
    what: ClassVar[LossKind]
    #: Where the device stops at the end of a take relative to the others (lower first): event
    #: sensors first, whose backlog is the longest to read.
    stop_order: ClassVar[int]

    def __init__(self, name: str) -> None:
        self.name = name
        self.trigger_in = 0
        """The trigger input its observations come on (event sensors)."""
        self.read_interval_s = 0.0
        """At most one read per this, once data came (event sensors: one read, one packet)."""
        self.anchors: HostAnchors | None = None
        """Where the device's clock can only be placed by when its data arrived (no trigger-in)."""

    @abstractmethod
    def open(self, spec: str) -> DevT:
        """The device behind `spec`, of this kind."""

    @abstractmethod
    def configure(self, dev: DevT) -> None:
        """Apply the config entry's settings."""

    @abstractmethod
    def required_capabilities(self, dev: DevT) -> frozenset[Capability]:
        """What the device must be able to do for its settings (checked by the preflight)."""

    @abstractmethod
    def read(self, dev: DevT, timeout_s: float) -> ItemT | None:
        """One delivery, or None when nothing came within `timeout_s`."""

    def stream_time_us(self, dev: DevT) -> int | None:
        """How far the device's stream has got in its own clock, data or not (None: unknown)."""
        return None

    def pace(self, done: threading.Event, asked: float, now: float) -> None:
        """After a read that delivered: wait out `read_interval_s` (the device buffers)."""
        if self.read_interval_s and not done.is_set() and (rest := self.read_interval_s - (now - asked)) > 0:
            done.wait(rest)

    @abstractmethod
    def times(self, item: ItemT) -> tuple[int | None, int | None]:
        """Device time of the first and the last thing in `item` (None: it holds no time)."""

    @abstractmethod
    def count(self, item: ItemT) -> int:
        """Frames or events in `item` (what is lost if it is)."""

    @abstractmethod
    def observations(self, item: ItemT) -> list[int]:
        """Device times of the trigger pulses `item` observed (a frame its exposure, a packet
        its rising edges on the trigger input)."""

    @abstractmethod
    def shifted(self, item: ItemT, us: int) -> ItemT:
        """`item` with its device times moved by `us` (a restarted clock re-tied)."""

    @abstractmethod
    def queue_item(self, item: ItemT) -> FrameItem | EventsItem:
        """`item` as the writer queue carries it."""

    @abstractmethod
    def gate(self, dev: DevT, window: TakeWindow, hold_s: float) -> WindowGate[ItemT]:
        """The gate that keeps what lies outside the take window out of the file."""

    @abstractmethod
    def add_to_take(self, take: TakeWriter, dev: DevT, settings_json: str) -> None:
        """Create the device's entry in the take."""

    def event_view(self, dev: DevT, stream: DeviceStream[Any]) -> tuple[EventArray, tuple[int, int]] | None:
        """The newest events written and the sensor's geometry, for the live view (None: none)."""
        return None

    def ballast_bytes(self, dev: DevT) -> int:
        """Bytes one pending item of the device may need when a full disk stops the take."""
        return 0

    def software_synced(self, dev: DevT) -> bool:
        """Whether its data is matched to pulses by host time alone."""
        return False


class CameraReading(Reading[RgbCamera, Frame]):
    """An RGB camera: one frame per read, its exposure start the trigger observation."""

    kind: ClassVar[SensorKind] = "rgb_camera"
    what: ClassVar[LossKind] = "frames"
    stop_order: ClassVar[int] = 1

    def __init__(self, name: str, settings: CameraSettings) -> None:
        super().__init__(name)
        self.settings = settings

    def open(self, spec: str) -> RgbCamera:
        return open_device("rgb_camera", spec)

    def configure(self, dev: RgbCamera) -> None:
        dev.configure(self.settings)

    def required_capabilities(self, dev: RgbCamera) -> frozenset[Capability]:
        return dev.required_capabilities(self.settings)

    def read(self, dev: RgbCamera, timeout_s: float) -> Frame | None:
        return dev.read_frame(timeout_s)

    def times(self, item: Frame) -> tuple[int | None, int | None]:
        return int(item.t_exposure_start_us), None

    def count(self, item: Frame) -> int:
        return 1

    def observations(self, item: Frame) -> list[int]:
        return [int(item.t_exposure_start_us)]

    def shifted(self, item: Frame, us: int) -> Frame:
        return dataclasses.replace(item, t_exposure_start_us=item.t_exposure_start_us + us)

    def queue_item(self, item: Frame) -> FrameItem:
        return FrameItem(self.name, item)

    def software_synced(self, dev: RgbCamera) -> bool:
        """No trigger input, or told to run free: its frames are matched to pulses by host time."""
        return Capability.HARDWARE_TRIGGER not in dev.capabilities or self.settings.trigger_mode != "hardware"

    def gate(self, dev: RgbCamera, window: TakeWindow, hold_s: float) -> FrameGate:
        timed = Capability.DEVICE_TIMESTAMPS in dev.capabilities and not self.software_synced(dev)
        mode: GateMode = "pulse_frames" if timed else "host"
        return FrameGate(self.name, mode, window, hold_s=hold_s)

    def add_to_take(self, take: TakeWriter, dev: RgbCamera, settings_json: str) -> None:
        # The take says how the camera was synchronized (recovery reads it back).
        sync = "software" if self.software_synced(dev) else "hardware"
        info = dev.info.model_copy(update={"facts": {**dev.info.facts, "sync": sync}})
        take.add_camera(
            self.name, info, dev.frame_shape, dev.frame_dtype, settings_json, pixel_format=dev.pixel_format
        )

    def ballast_bytes(self, dev: RgbCamera) -> int:
        return math.prod(dev.frame_shape) * dev.frame_dtype.itemsize


class EventReading(Reading[EventSensor, EventPacket]):
    """An event sensor: packets of events and trigger-in edges, read at most once per
    `read_interval_ms`; its rising edges on its trigger input are its trigger observations."""

    kind: ClassVar[SensorKind] = "event_sensor"
    what: ClassVar[LossKind] = "events"
    stop_order: ClassVar[int] = 0

    def __init__(self, name: str, settings: EventSensorSettings, read_interval_s: float = 0.0) -> None:
        super().__init__(name)
        self.settings = settings
        self.trigger_in = settings.trigger_in_channel
        self.read_interval_s = read_interval_s
        self.anchors = None if settings.enable_trigger_in else HostAnchors()

    def open(self, spec: str) -> EventSensor:
        return open_device("event_sensor", spec)

    def configure(self, dev: EventSensor) -> None:
        dev.configure(self.settings)

    def required_capabilities(self, dev: EventSensor) -> frozenset[Capability]:
        return dev.required_capabilities(self.settings)

    def read(self, dev: EventSensor, timeout_s: float) -> EventPacket | None:
        return dev.read_events(timeout_s)

    def stream_time_us(self, dev: EventSensor) -> int | None:
        return dev.stream_time_us

    def times(self, item: EventPacket) -> tuple[int | None, int | None]:
        span = item.span
        if span.n:
            return span.t_first, span.t_last
        return (int(item.triggers.t[0]), None) if len(item.triggers) else (None, None)

    def count(self, item: EventPacket) -> int:
        return item.n_events

    def observations(self, item: EventPacket) -> list[int]:
        if not len(item.triggers):
            return []
        return item.triggers.rising(self.trigger_in).t.tolist()

    def shifted(self, item: EventPacket, us: int) -> EventPacket:
        raw = item.raw  # its words are not rewritten: the chunk says what was added
        return item.with_shift(
            us, None if raw is None else dataclasses.replace(raw, shift_us=raw.shift_us + us)
        )

    def queue_item(self, item: EventPacket) -> EventsItem:
        return EventsItem(self.name, item)

    def event_view(
        self, dev: EventSensor, stream: DeviceStream[Any]
    ) -> tuple[EventArray, tuple[int, int]] | None:
        return (stream.recent_events(), dev.geometry) if stream.recent_packets else None

    def gate(self, dev: EventSensor, window: TakeWindow, hold_s: float) -> EventGate:
        mode: GateMode = "trigger_in" if self.settings.enable_trigger_in else "host"
        return EventGate(self.name, mode, window, trigger_channel=self.trigger_in, hold_s=hold_s)

    def add_to_take(self, take: TakeWriter, dev: EventSensor, settings_json: str) -> None:
        w, h = dev.geometry
        fmt = dev.evt_format if dev.delivers_evt_words else None
        take.add_event_sensor(self.name, dev.info, w, h, settings_json, fmt)
