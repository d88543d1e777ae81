"""`rigd convert`: RAW/DAT recordings to takes and back, streaming in constant memory.

A recording converted to a take keeps the sensor's own clock (there is no trigger box to tie
it to): the take's clock map is the identity and its report says so. Converting back writes
the events and trigger edges of one sensor, re-encoded in the chosen EVT format.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np

from drivers.evt import (
    Evt2Encoder,
    Evt3Encoder,
    Evt21Encoder,
    RawHeader,
    RawReader,
    read_dat,
    write_dat,
)
from rigd import __version__
from rigd.core.devices import DeviceInfo
from rigd.core.errors import RigdError
from rigd.core.events import TriggerEvents
from rigd.core.schema import SyncReport
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.take.reader import Take
from rigd.take.writer import TakeWriter

log = logging.getLogger(__name__)

_CHUNK_EVENTS = 1 << 20
Progress = Callable[[int], None]


class ConvertError(RigdError):
    """A conversion cannot be done as asked (unknown extension, missing sensor, ...)."""


def convert(
    src: Path,
    dst: Path,
    *,
    sensor: str | None = None,
    fmt: str = "evt3",
    strict: bool = False,
    on_progress: Progress | None = None,
) -> int:
    """Convert by extension (.raw/.dat <-> .h5); returns the number of events written."""
    s, d = src.suffix.lower(), dst.suffix.lower()
    if s in (".raw", ".dat") and d in (".h5", ".hdf5"):
        return recording_to_take(src, dst, sensor=sensor or "ev0", strict=strict, on_progress=on_progress)
    if s in (".h5", ".hdf5") and d in (".raw", ".dat"):
        return take_to_recording(src, dst, sensor=sensor, fmt=fmt, on_progress=on_progress)
    raise ConvertError(f"cannot convert {src.name} to {dst.name}: use .raw/.dat -> .h5 or .h5 -> .raw/.dat")


def recording_to_take(
    src: Path, dst: Path, *, sensor: str = "ev0", strict: bool = False, on_progress: Progress | None = None
) -> int:
    if dst.exists():
        raise ConvertError(f"{dst} exists; not overwriting a take")
    if src.suffix.lower() == ".dat":
        dat_hdr, ev = read_dat(src, strict=strict)
        width = dat_hdr.width or (int(ev.x.max()) + 1 if len(ev) else 1)
        height = dat_hdr.height or (int(ev.y.max()) + 1 if len(ev) else 1)
        chunks = iter([(ev, TriggerEvents.empty())])
        fields, fmt, stats = dict(dat_hdr.fields), "dat", None
    else:
        reader = RawReader(src, strict=strict)
        width, height = reader.header.width, reader.header.height
        chunks = ((d.events, d.triggers) for d in reader)
        fields, fmt, stats = reader.header.fields, reader.header.fmt, reader
    info = DeviceInfo(
        kind="event_sensor",
        spec=f"file://{src.resolve()}",
        vendor="file",
        serial=fields.get("serial_number", ""),
        firmware=f"format={fmt}",
    )
    n = 0
    with TakeWriter(
        dst,
        rig_config_json=json.dumps({"converted_from": str(src), "header": fields}),
        take_id=dst.stem,
        config=WriterConfig(),
        rigd_version=__version__,
    ) as writer:
        try:
            writer.add_event_sensor(
                sensor, info, width, height, json.dumps({"format": fmt, "header": fields})
            )
            for ev, tr in chunks:
                if len(ev):
                    writer.append_events(sensor, ev)
                if len(tr):
                    writer.append_triggers(sensor, tr)
                n += len(ev)
                if on_progress:
                    on_progress(n)
            warnings = [
                "converted recording: times are the sensor's own clock (identity map), no trigger box"
            ]
            skipped = {k: v for k, v in (stats.stats.items() if stats else []) if v}
            if skipped:
                warnings.append(f"decoder skipped invalid data: {skipped}")
            report = SyncReport(
                rate_hz=0.0, n_pulses=0, t_first_pulse_us=None, t_last_pulse_us=None, warnings=warnings
            )
            writer.finalize({sensor: ClockMap.identity()}, {}, report)
        except BaseException as exc:
            writer.fail(f"convert failed: {exc!r}")
            raise
    log.info("converted %s -> %s: %d events", src, dst, n)
    return n


def take_to_recording(
    src: Path, dst: Path, *, sensor: str | None = None, fmt: str = "evt3", on_progress: Progress | None = None
) -> int:
    if dst.exists():
        raise ConvertError(f"{dst} exists; not overwriting")
    with Take(src) as take:
        if sensor is None:
            if len(take.event_sensors) != 1:
                raise ConvertError(f"{src} has event sensors {take.event_sensors}: choose one with --sensor")
            sensor = take.event_sensors[0]
        if sensor not in take.event_sensors:
            raise ConvertError(f"{src} has no event sensor {sensor!r}; it has {take.event_sensors}")
        width, height = take.geometry(sensor)
        total = take.event_count(sensor)
        triggers = take.triggers(sensor)
        if dst.suffix.lower() == ".dat":
            ev = take.events_by_index(sensor, 0, total)
            write_dat(dst, ev, width=width, height=height)
            return len(ev)
        encoder: Evt3Encoder | Evt2Encoder | Evt21Encoder
        if fmt == "evt3":
            encoder = Evt3Encoder()
        elif fmt == "evt2":
            encoder = Evt2Encoder()
        elif fmt == "evt21":
            encoder = Evt21Encoder()
        else:
            raise ConvertError(f"unknown EVT format {fmt!r}; choose evt3, evt2 or evt21")
        n_trig = 0
        with dst.open("wb") as f:
            f.write(
                RawHeader(fmt=fmt, width=width, height=height, fields={"converted_from": src.name}).to_bytes()
            )
            for start in range(0, max(total, 1), _CHUNK_EVENTS):
                ev = take.events_by_index(sensor, start, min(start + _CHUNK_EVENTS, total))
                last = start + len(ev) >= total
                t_hi = int(ev.t[-1]) if len(ev) else None
                upto = (
                    len(triggers) if last or t_hi is None else int(np.searchsorted(triggers.t, t_hi, "right"))
                )
                tr = triggers[n_trig:upto]
                n_trig = upto
                f.write(encoder.encode(ev, tr))
                if on_progress:
                    on_progress(start + len(ev))
        if not total and not len(triggers):
            log.warning("%s: sensor %s has no events; wrote a header-only file", src, sensor)
    return total
