"""One stream object per device kind: what the channel and the writer thread need to know of it.

A camera's frames, an event sensor's packets and the trigger box's pulse records differ in how
they are opened, counted, written and observed; instead of asking "what kind is this?" at
every step, the channel and the writer loop call the device's stream. The writer thread owns
the stream's observations: what reached the file (the trigger observations the sync engine
fits, counts, the newest frame and event packets for the live views) is recorded here as the
item lands, with no call back into the channel (decision 0023).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable
from typing import Any, ClassVar, Generic, TypeVar

import numpy as np
from numpy.typing import NDArray

from rigd.app.capture.items import EventsItem, FrameItem, PulsesItem
from rigd.app.capture.live import LiveStats, Observations
from rigd.core.events import EventArray, EventPacket
from rigd.core.frames import Frame
from rigd.core.kinds import SensorKind
from rigd.core.schema import LossKind
from rigd.sync import DeviceObservations
from rigd.take.writer import TakeWriter

#: Recent event packets kept for the live event thumbnails, and the events decoded of them at most.
RECENT_PACKETS = 8
RECENT_EVENTS = 500_000

ItemT = TypeVar("ItemT", FrameItem, EventsItem, PulsesItem)


class Stream(ABC, Generic[ItemT]):
    """A device's items from the queue to the file, and what the take keeps of them."""

    what: ClassVar[LossKind]

    def __init__(self, name: str, live: LiveStats) -> None:
        self.name = name
        self.live = live
        self.written = 0
        """Items (frames, events, pulse records) that reached the file."""

    @abstractmethod
    def write(self, writer: TakeWriter, item: ItemT) -> None:
        """Hand the item to the take's sink for this device."""

    def landed(self, item: ItemT) -> None:
        """The item reached the file (writer thread): count it."""
        self.written += item.count


class TriggerStream(Stream[PulsesItem]):
    """The trigger box's pulse records (counted by its channel as they arrive)."""

    what: ClassVar[LossKind] = "pulses"

    def write(self, writer: TakeWriter, item: PulsesItem) -> None:
        writer.append_pulses(item.batch)


class DeviceStream(Stream[ItemT]):
    """A camera or an event sensor: observed for the sync engine."""

    kind: ClassVar[SensorKind]
    #: After the last pulse, how many trigger periods of data past it the device owes before
    #: it counts as drained.
    drain_periods: ClassVar[int]
    #: Whether its trigger observations carry the device's frame counter (gaps: lost frames).
    frame_counters: ClassVar[bool] = False

    def __init__(self, name: str, live: LiveStats, trigger_in: int = 0) -> None:
        super().__init__(name, live)
        self.trigger_in = trigger_in
        self.obs = Observations()
        """Trigger observations of what reached the file (one per pulse: small)."""
        self.latest_frame: Frame | None = None
        """The newest frame written (cameras), for the live view."""
        self.recent_packets: list[EventPacket] = []
        """The newest event packets written (event sensors), for the live thumbnails (their
        events decoded only when a view asks: `recent_events`)."""

    def recent_events(self) -> EventArray:
        """The newest packets' events, at most `RECENT_EVENTS` packets' worth (decoded now
        where the sensor only scanned them)."""
        parts: list[EventArray] = []
        n = 0
        for packet in reversed(list(self.recent_packets)):
            if n >= RECENT_EVENTS:
                break
            parts.append(packet.events)
            n += packet.n_events
        return EventArray.concatenate(parts[::-1])

    def sync_observations(
        self, anchors: tuple[NDArray[np.int64], NDArray[np.int64]] | None
    ) -> DeviceObservations:
        """What the sync engine fits this device's clock on: its trigger observations (a
        camera's with its frame counters), and host `anchors` where it has no trigger input."""
        t, host, counter = self.obs.arrays()
        return DeviceObservations(
            self.name, self.kind, t, host, counter if self.frame_counters else None, anchors
        )


class CameraStream(DeviceStream[FrameItem]):
    """An RGB camera: one frame per item, one trigger observation (its exposure) per frame."""

    what: ClassVar[LossKind] = "frames"
    kind: ClassVar[SensorKind] = "rgb_camera"
    drain_periods: ClassVar[int] = 0
    frame_counters: ClassVar[bool] = True

    def write(self, writer: TakeWriter, item: FrameItem) -> None:
        writer.append_frame(item.device, item.frame)

    def landed(self, item: FrameItem) -> None:
        frame = item.frame
        self.obs.t.append(frame.t_exposure_start_us)
        self.obs.host.append(frame.host_time_ns)
        self.obs.counter.append(frame.frame_counter)
        self.written += 1
        self.live.total += 1
        self.latest_frame = frame


class EventStream(DeviceStream[EventsItem]):
    """An event sensor: packets of events and trigger-in edges; its rising edges on its
    trigger-in channel are its trigger observations."""

    what: ClassVar[LossKind] = "events"
    kind: ClassVar[SensorKind] = "event_sensor"
    drain_periods: ClassVar[int] = 2

    def write(self, writer: TakeWriter, item: EventsItem) -> None:
        writer.append_packet(item.device, item.packet)

    def landed(self, item: EventsItem) -> None:
        packet = item.packet
        if packet.n_events:
            self.recent_packets.append(packet)
            del self.recent_packets[:-RECENT_PACKETS]
        if len(packet.triggers):
            rising = packet.triggers.rising(self.trigger_in)
            self.obs.t.extend(rising.t.tolist())
            self.obs.host.extend([packet.host_time_ns] * len(rising))
        self.written += packet.n_events
        self.live.total += packet.n_events


def writer_streams(devices: Iterable[DeviceStream[Any]], trigger_live: LiveStats) -> dict[str, Stream[Any]]:
    """What the writer loop writes through, by the name on the queue items (the box's pulse
    records come as "trigger")."""
    streams: dict[str, Stream[Any]] = {s.name: s for s in devices}
    streams[PulsesItem.device] = TriggerStream(PulsesItem.device, trigger_live)
    return streams
