"""The reading part of a device channel: what a device kind must answer for the channel's one
loop (how the device is opened, configured, read and entered in the take, and what its items
say about time). The kinds' readings are in `kinds`, beside the factory that composes them.

The channel (`channel.DeviceChannel`) runs the same loop for every kind: read, re-tie a
restarted clock, pass the window gate, shed under overload, queue for the writer. Everything in
that loop that depends on what the device is (a camera's frames, an event sensor's packets) is
asked of this part, which the factory (`kinds`) chose once; the loop never tests a kind
(decision 0028).
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from typing import Any, ClassVar, Generic, TypeVar

from drivers.base import Capability, EventSensor, RgbCamera
from rigd.app.capture.gate import WindowGate
from rigd.app.capture.items import EventsItem, FrameItem
from rigd.app.capture.live import HostAnchors
from rigd.app.capture.streams import DeviceStream
from rigd.app.capture.window import TakeWindow
from rigd.core.events import EventArray, EventPacket
from rigd.core.frames import Frame
from rigd.core.host_clock import HostClock
from rigd.core.kinds import SensorKind
from rigd.core.schema import LossKind
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
    def gate(self, dev: DevT, window: TakeWindow, hold_s: float, clock: HostClock) -> WindowGate[ItemT]:
        """The gate that keeps what lies outside the take window out of the file; `clock` is
        the one the items' host times are on (it times the gate's hold)."""

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
