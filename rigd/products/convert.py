"""`rigd convert`: RAW/DAT recordings to takes and back, streaming in constant memory (rosbag2
bags to takes: rigd.products.ros.bag_convert).

A recording converted to a take keeps the sensor's own clock (there is no trigger box to tie
it to): the take's clock map is the identity and its report says so. What the decoder skipped
(corrupt words, events that would go back in time) becomes a loss record naming the first byte
offsets; a time jump back that it accepted (two recordings joined) becomes a warning naming where
and by how much later times were shifted. An input that cannot be read, or that decodes to nothing,
is a ConvertError naming the file, and the take being written is removed: convert leaves no
half-done take behind. Converting back writes the events and trigger edges of one sensor,
re-encoded in the chosen EVT format.
"""

from __future__ import annotations

import itertools
import json
import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from rigd import __version__
from rigd.core.devices import DeviceInfo
from rigd.core.errors import EventDataError, RigdError
from rigd.core.events import EventArray, TriggerEvents
from rigd.core.schema import LossRecord, SyncReport
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.evt import (
    DatHeader,
    Evt2Encoder,
    Evt3Encoder,
    Evt21Encoder,
    RawHeader,
    RawReader,
    read_dat,
    write_dat,
)
from rigd.take.reader import Take
from rigd.take.seal import fail_take, finalize_take
from rigd.take.writer import TakeWriter

log = logging.getLogger(__name__)


@contextmanager
def removed_if_unfinished(src: Path, dst: Path) -> Iterator[None]:
    """A conversion that fails leaves no half-written take at `dst` (it was not there before)."""
    try:
        yield
    except BaseException:
        if dst.exists():
            log.warning("convert %s failed; removing the unfinished take %s", src, dst)
            dst.unlink()
        raise


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
    triggers: bool = True,
    on_progress: Progress | None = None,
) -> int:
    """Convert by extension (.raw/.dat <-> .h5, rosbag2 .db3/.mcap or bag directory -> .h5);
    returns the number of events written."""
    s, d = src.suffix.lower(), dst.suffix.lower()
    if (s in (".db3", ".mcap") or (src.is_dir() and s not in (".raw", ".dat"))) and d in (".h5", ".hdf5"):
        from rigd.products.ros.bag_convert import bag_to_take

        return bag_to_take(src, dst, on_progress=on_progress)
    if s in (".raw", ".dat") and d in (".h5", ".hdf5"):
        return recording_to_take(src, dst, sensor=sensor or "ev0", strict=strict, on_progress=on_progress)
    if s in (".h5", ".hdf5") and d in (".raw", ".dat"):
        return take_to_recording(src, dst, sensor=sensor, fmt=fmt, triggers=triggers, on_progress=on_progress)
    raise ConvertError(
        f"cannot convert {src.name} to {dst.name}: use .raw/.dat -> .h5, .h5 -> .raw/.dat "
        "or a rosbag2 bag (.db3, .mcap or its directory) -> .h5"
    )


def _skip_text(skipped: dict[str, int], offsets: list[int]) -> str:
    return f"{skipped}, first at byte offsets {offsets}"


def _open_recording(
    src: Path, strict: bool
) -> tuple[Iterator[tuple[EventArray, TriggerEvents]], int, int, dict[str, str], str, RawReader | DatHeader]:
    """Chunks, geometry, header fields, format and what reports the skips; a ConvertError naming
    the file when it cannot be read as a recording."""
    if src.is_dir():
        raise ConvertError(f"{src}: is a directory, not a recording")
    try:
        if src.stat().st_size == 0:
            raise ConvertError(f"{src}: empty file, not a recording")
        if src.suffix.lower() == ".dat":
            dat_hdr, ev = read_dat(src, strict=strict)
            width = dat_hdr.width or (int(ev.x.max()) + 1 if len(ev) else 1)
            height = dat_hdr.height or (int(ev.y.max()) + 1 if len(ev) else 1)
            return iter([(ev, TriggerEvents.empty())]), width, height, dict(dat_hdr.fields), "dat", dat_hdr
        reader = RawReader(src, strict=strict)
    except OSError as exc:
        raise ConvertError(f"{src}: cannot read: {exc.strerror or exc}") from exc
    return (
        _decoded(src, reader),
        reader.header.width,
        reader.header.height,
        reader.header.fields,
        reader.header.fmt,
        reader,
    )


def _decoded(src: Path, reader: RawReader) -> Iterator[tuple[EventArray, TriggerEvents]]:
    """The reader's chunks; a strict-mode decode error names the file (the decoder's does not)."""
    try:
        for d in reader:
            yield d.events, d.triggers
    except EventDataError as exc:
        raise ConvertError(f"{src}: {exc}") from exc


def _skips(source: RawReader | DatHeader) -> tuple[dict[str, int], list[int]]:
    """What the decoder skipped, by kind, and the byte offsets of the first few."""
    if isinstance(source, RawReader):
        return {k: v for k, v in source.stats.items() if v}, source.decoder.skipped_offsets
    return dict(source.skipped), source.skipped_offsets


def _jump_lines(source: RawReader | DatHeader) -> list[str]:
    """The take's warning lines for the decoder's accepted time jumps back (DAT files have none)."""
    if not isinstance(source, RawReader):
        return []
    dec = source.decoder
    lines = [j.line(dec.fmt) for j in dec.jumps]
    if dec.time_jumps > len(dec.jumps):
        lines.append(f"{dec.fmt} stream time jumped back {dec.time_jumps - len(dec.jumps)} more time(s)")
    return lines


def _first_data(
    src: Path, chunks: Iterator[tuple[EventArray, TriggerEvents]], source: RawReader | DatHeader
) -> Iterator[tuple[EventArray, TriggerEvents]]:
    """The chunks from the first that holds data on (decoding up to it in constant memory); a
    ConvertError when none does, so an input with nothing to convert never creates a take."""
    for ev, tr in chunks:
        if len(ev) or len(tr):
            return itertools.chain([(ev, tr)], chunks)
    skipped, offsets = _skips(source)
    why = f"the decoder skipped {_skip_text(skipped, offsets)}" if skipped else "it holds no event data"
    raise ConvertError(f"{src}: no events decoded: {why}")


def recording_to_take(
    src: Path, dst: Path, *, sensor: str = "ev0", strict: bool = False, on_progress: Progress | None = None
) -> int:
    """Write a RAW/DAT recording as a take; returns the events written."""
    if dst.exists():
        raise ConvertError(f"{dst} exists; not overwriting a take")
    chunks, width, height, fields, fmt, source = _open_recording(src, strict)
    chunks = _first_data(src, chunks, source)  # before the take exists: nothing to undo
    with removed_if_unfinished(src, dst):
        n = _write_take(src, dst, sensor, chunks, (width, height), fields, fmt, source, on_progress)
    log.info("converted %s -> %s: %d events", src, dst, n)
    return n


def _write_take(
    src: Path,
    dst: Path,
    sensor: str,
    chunks: Iterator[tuple[EventArray, TriggerEvents]],
    geometry: tuple[int, int],
    fields: dict[str, str],
    fmt: str,
    source: RawReader | DatHeader,
    on_progress: Progress | None,
) -> int:
    """Write the chunks as one sensor's data and finalize with the skips as losses; a failure
    marks the take failed (the caller removes it)."""
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
            writer.add_event_sensor(sensor, info, *geometry, json.dumps({"format": fmt, "header": fields}))
            for ev, tr in chunks:
                if len(ev):
                    writer.append_events(sensor, ev)
                if len(tr):
                    writer.append_triggers(sensor, tr)
                n += len(ev)
                if on_progress:
                    on_progress(n)
            skipped, offsets = _skips(source)
            warnings = [
                "converted recording: times are the sensor's own clock (identity map), no trigger box"
            ]
            losses = []
            if skipped:
                text = _skip_text(skipped, offsets)
                warnings.append(f"decoder skipped invalid data: {text}")
                losses.append(
                    LossRecord(
                        device=sensor,
                        what="events",
                        count=sum(skipped.values()),
                        reason=f"EVT decoder skipped invalid data in {src.name}: {text}",
                    )
                )
                log.warning("%s: decoder skipped %s; recorded as losses in %s", src, text, dst)
            warnings += _jump_lines(source)  # kept, with later times shifted: said, not lost
            report = SyncReport(
                rate_hz=0.0,
                n_pulses=0,
                t_first_pulse_us=None,
                t_last_pulse_us=None,
                warnings=warnings,
                losses=losses,
            )
            finalize_take(writer, {sensor: ClockMap.identity()}, {}, report)
        except BaseException as exc:
            fail_take(writer, f"convert failed: {exc!r}")
            raise
    return n


def take_to_recording(
    src: Path,
    dst: Path,
    *,
    sensor: str | None = None,
    fmt: str = "evt3",
    triggers: bool = True,
    on_progress: Progress | None = None,
) -> int:
    """Write one sensor's events (and, unless `triggers` is False, its trigger edges as EXT_TRIGGER
    words: some readers stop at them) re-encoded in `fmt`: evt3, evt2, evt21 (IMX636's
    half-swapped words, header `endianness=legacy`) or evt21_le (little-endian 64-bit words)."""
    if dst.exists():
        raise ConvertError(f"{dst} exists; not overwriting")
    with Take(src) as take:
        if sensor is None:
            if len(take.event_sensors) != 1:
                raise ConvertError(f"{src} has event sensors {take.event_sensors}: choose one with --sensor")
            sensor = take.event_sensors[0]
        if sensor not in take.event_sensors:
            raise ConvertError(f"{src} has no event sensor {sensor!r}; it has {take.event_sensors}")
        series = take.sensor(sensor)
        width, height = series.geometry
        total = series.count
        edges = series.triggers if triggers else TriggerEvents.empty()
        if dst.suffix.lower() == ".dat":
            ev = series.by_index(0, total)
            write_dat(dst, ev, width=width, height=height)
            return len(ev)
        encoder: Evt3Encoder | Evt2Encoder | Evt21Encoder
        if fmt == "evt3":
            encoder = Evt3Encoder()
        elif fmt == "evt2":
            encoder = Evt2Encoder()
        elif fmt in ("evt21", "evt21_le"):
            encoder = Evt21Encoder(little_endian=fmt == "evt21_le")
        else:
            raise ConvertError(f"unknown EVT format {fmt!r}; choose evt3, evt2, evt21 or evt21_le")
        n_trig = 0
        with dst.open("wb") as f:
            f.write(
                RawHeader(fmt=fmt, width=width, height=height, fields={"converted_from": src.name}).to_bytes()
            )
            for start in range(0, max(total, 1), _CHUNK_EVENTS):
                ev = series.by_index(start, min(start + _CHUNK_EVENTS, total))
                last = start + len(ev) >= total
                t_hi = int(ev.t[-1]) if len(ev) else None
                upto = len(edges) if last or t_hi is None else int(np.searchsorted(edges.t, t_hi, "right"))
                tr = edges[n_trig:upto]
                n_trig = upto
                f.write(encoder.encode(ev, tr))
                if on_progress:
                    on_progress(start + len(ev))
        if not total and not len(edges):
            log.warning("%s: sensor %s has no events; wrote a header-only file", src, sensor)
    return total
