"""One interface for the two ways an event sensor is stored, and the one place that chooses.

A sensor's events land either as DSEC-compatible x/y/p/t columns (`rigd.take.sinks.EventSink`)
or as the EVT words it sent (`rigd.take.evt_sink.EvtWordsSink`). The writer, finalize, flush,
fail and resume ask the store (`EventStore`) for what they need instead of testing its class;
`event_store` is the only code that knows which class a sensor gets.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import h5py

from rigd.core.events import EventArray, EventPacket, TriggerEvents
from rigd.core.layout import Events, Storage
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.evt import FORMATS as EVT_FORMATS
from rigd.take.evt_read import is_evt_words
from rigd.take.evt_sink import EvtWordsSink
from rigd.take.sinks import DeviceWriteStats, EventSink

if TYPE_CHECKING:
    from rigd.take.finalize import Finalizer

__all__ = ["EventStore", "NewSensor", "event_store"]


class EventStore(Protocol):
    """An event sensor's storage in the take: its group, buffers and what finalize does to it."""

    name: str
    group: h5py.Group
    n_written: int
    """Events stored: all of them once the buffers had their final write (finalize, fail,
    close); while recording, a store may count only those in its main datasets."""
    trig: dict[str, h5py.Dataset]
    """The trigger-in edge datasets (`<sensor>/trigger`)."""
    appendable: bool
    """False for a resumed take: it can be finalized or failed, not appended to."""
    stats: DeviceWriteStats

    def add_events(self, events: EventArray, path: Path) -> None:
        """Buffer decoded events (device clock), checked whole before any is kept; a store of
        EVT words refuses them (TakeError): it takes packets."""

    def append_packet(self, packet: EventPacket, path: Path) -> None:
        """Store a packet's events (as the store keeps them) and its trigger edges."""

    def add_triggers(self, triggers: TriggerEvents, host_time_ns: int | None) -> None:
        """Buffer trigger-in edges (device clock)."""

    def write_buffers(self, *, final: bool) -> None:
        """Write what is buffered: to the main datasets up to the last whole chunk and the rest
        to the tail slots (a flush), or all of it (`final`: close, fail, finalize)."""

    def drop_tails(self) -> None:
        """Drop the tail slots once everything is in the main datasets."""

    def set_compress(self, on: bool) -> None:
        """Whether later chunks are compressed by the writer thread (while it is behind, not)."""

    def first_time(self) -> int | None:
        """Device time of the first event, buffered or stored (None: none yet); before
        finalize, which rewrites the stored times."""

    def events_in_take(self) -> int:
        """Events a reader of the take sees."""

    def datasets(self) -> list[h5py.Dataset]:
        """Every dataset the store writes (for the stored-bytes count)."""

    def finalize_times(self, finalizer: Finalizer, cmap: ClockMap, t_offset: int) -> None:
        """Tie the stored times to rig time with `cmap` and `t_offset` (idempotent: a resumed
        finalize calls it again)."""


@dataclass(frozen=True, slots=True)
class NewSensor:
    """A sensor being added to a new take: its geometry and the EVT format its packets carry
    (None: no words)."""

    width: int
    height: int
    evt_format: str | None


def event_store(
    name: str,
    group: h5py.Group,
    where: str,
    config: WriterConfig,
    *,
    new: NewSensor | None = None,
    column_opts: dict[str, Any] | None = None,
) -> EventStore:
    """The store of sensor `name` in `group`: laid out for a `new` sensor as `config` and its
    packets allow (EVT words only where both do; the columns' group says why otherwise), or,
    for a resumed take (`new` None), as the group says it was written."""
    if new is None:
        if is_evt_words(group):
            return EvtWordsSink.reopen(name, group, where)
        return EventSink.reopen(name, group, where, config.event_chunk)
    if new.evt_format in EVT_FORMATS and config.event_storage == Storage.EVT_WORDS:
        return EvtWordsSink.create(name, group, new.width, new.height, new.evt_format)
    group.attrs[Events.STORAGE] = Storage.COLUMNS
    if config.event_storage == Storage.EVT_WORDS:
        why = "carry no EVT words" if new.evt_format is None else f"are {new.evt_format}, not EVT words"
        group.attrs[Events.STORAGE_NOTE] = f"columns: the sensor's packets {why}"
    return EventSink.create(name, group, new.width, new.height, config.event_chunk, column_opts or {})
