"""The device kinds of the capture path: each kind's reading part, and the one factory that
makes each camera and event sensor of a rig config a channel of its kind's parts (decision 0028).

A device kind is a set of parts: its `reading` (open, configure, read, what its items say about
time, its take entry), its window `gate` (made by the reading once the window can be placed),
its load `shedding` (event sensors shed whole time slices; a camera's frame is kept or counted
lost at the queue) and its writer-side `stream`. This module is the only place that maps a kind
to them; the channel, the session, finalize and the service ask the parts. A fourth device kind
is a reading, a stream and a line here.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar

from drivers.base import Capability, EventSensor, RgbCamera
from drivers.registry import open_device
from rigd.app.capture.channel import ChannelContext, DeviceChannel
from rigd.app.capture.gate import EventGate, FrameGate, GateMode
from rigd.app.capture.items import EventsItem, FrameItem
from rigd.app.capture.live import HostAnchors, LiveStats
from rigd.app.capture.overload import KeepAll, SliceShedder
from rigd.app.capture.reading import Reading
from rigd.app.capture.streams import CameraStream, DeviceStream, EventStream
from rigd.app.capture.window import TakeWindow
from rigd.app.config import CameraConfig, EventSensorConfig, RigConfig
from rigd.core.events import EventArray, EventPacket
from rigd.core.frames import Frame
from rigd.core.host_clock import HostClock
from rigd.core.kinds import SensorKind
from rigd.core.schema import LossKind
from rigd.core.settings import CameraSettings, EventSensorSettings
from rigd.take.writer import TakeWriter


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

    def gate(self, dev: RgbCamera, window: TakeWindow, hold_s: float, clock: HostClock) -> FrameGate:
        timed = Capability.DEVICE_TIMESTAMPS in dev.capabilities and not self.software_synced(dev)
        mode: GateMode = "pulse_frames" if timed else "host"
        return FrameGate(self.name, mode, window, hold_s=hold_s, clock_ns=clock.now_ns)

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

    def gate(self, dev: EventSensor, window: TakeWindow, hold_s: float, clock: HostClock) -> EventGate:
        mode: GateMode = "trigger_in" if self.settings.enable_trigger_in else "host"
        return EventGate(
            self.name, mode, window, trigger_channel=self.trigger_in, hold_s=hold_s, clock_ns=clock.now_ns
        )

    def add_to_take(self, take: TakeWriter, dev: EventSensor, settings_json: str) -> None:
        w, h = dev.geometry
        fmt = dev.evt_format if dev.delivers_evt_words else None
        take.add_event_sensor(self.name, dev.info, w, h, settings_json, fmt)


def camera_channel(cam: CameraConfig, ctx: ChannelContext) -> DeviceChannel[RgbCamera, Frame]:
    """An RGB camera's channel (opens the camera)."""
    reading = CameraReading(cam.name, cam.settings)
    stream = CameraStream(cam.name, LiveStats(reading.kind))
    return DeviceChannel(cam.name, cam.spec, cam.settings.model_dump_json(), reading, stream, KeepAll(), ctx)


def event_channel(
    sen: EventSensorConfig, ctx: ChannelContext, max_lag_s: float
) -> DeviceChannel[EventSensor, EventPacket]:
    """An event sensor's channel (opens the sensor); it sheds slices when the writer falls
    behind by more than `max_lag_s` or the queue fills."""
    reading = EventReading(sen.name, sen.settings, sen.read_interval_ms / 1000)
    stream = EventStream(sen.name, LiveStats(reading.kind), reading.trigger_in)
    shedding = SliceShedder(sen.name, ctx.ledger, ctx.faults, max_lag_s=max_lag_s)
    return DeviceChannel(sen.name, sen.spec, sen.settings.model_dump_json(), reading, stream, shedding, ctx)


def open_channels(config: RigConfig, ctx: ChannelContext, opened: dict[str, DeviceChannel[Any, Any]]) -> None:
    """Each device of the rig as a channel, cameras first, in config order, into `opened` as each
    opens, so a caller keeps (and closes) the ones already open when a later one fails to."""
    for cam in config.cameras:
        opened[cam.name] = camera_channel(cam, ctx)
    for sen in config.event_sensors:
        opened[sen.name] = event_channel(sen, ctx, config.writer.overload_max_lag_s)
