"""The one factory of the capture path: each camera and event sensor of a rig config becomes a
channel composed of its kind's parts (decision 0028).

A device kind is a set of parts: its `reading` (open, configure, read, what its items say about
time, its take entry), its window `gate` (made by the reading once the window can be placed),
its load `shedding` (event sensors shed whole time slices; a camera's frame is kept or counted
lost at the queue) and its writer-side `stream`. This module is the only place that maps a kind
to them; the channel, the session, finalize and the service ask the parts. A fourth device kind
is a reading, a stream and a line here.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from drivers.base import EventSensor, RgbCamera
from rigd.app.capture.channel import ChannelContext, DeviceChannel
from rigd.app.capture.live import LiveStats
from rigd.app.capture.overload import KeepAll, SliceShedder
from rigd.app.capture.reading import CameraReading, EventReading
from rigd.app.capture.streams import CameraStream, EventStream
from rigd.app.config import CameraConfig, EventSensorConfig, RigConfig
from rigd.core.events import EventPacket
from rigd.core.frames import Frame


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


def device_channels(config: RigConfig, ctx: ChannelContext) -> Iterator[tuple[str, DeviceChannel[Any, Any]]]:
    """Each device of the rig as a channel, cameras first, in config order; opened one at a
    time, so a caller keeps the ones already open when a later one fails to."""
    for cam in config.cameras:
        yield cam.name, camera_channel(cam, ctx)
    for sen in config.event_sensors:
        yield sen.name, event_channel(sen, ctx, config.writer.overload_max_lag_s)
