"""Prophesee DAT files (Event2D/CD): `% ` header lines, 2 bytes (event type, size=8), records.

Each record is u32 t (us) then u32 with x in bits [13:0], y in [27:14], p in [31:28]. Decoding is
a numpy view over the records, so there is no per-event Python loop. Records are kept in time
order like the EVT decoders' output: a record earlier than one before it (a corrupt t) is dropped
and counted as non_monotonic_time, and so is a lone record jumping ahead of its successors, which
would otherwise hold back every record after it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from rigd.core.errors import EventDataError
from rigd.core.events import EventArray
from rigd.evt.errors import KIND_NAMES, MAX_SKIP_OFFSETS, NON_MONOTONIC_TIME, TRUNCATED, EvtDecodeError
from rigd.evt.raw_header import read_header_lines

log = logging.getLogger(__name__)

_RECORD = np.dtype([("t", "<u4"), ("d", "<u4")])
CD_EVENT_TYPE = 0x0C


@dataclass(slots=True)
class DatHeader:
    """Header lines (`key value`), the event type byte and, when given, the geometry."""

    fields: dict[str, str] = field(default_factory=dict)
    event_type: int = CD_EVENT_TYPE
    event_size: int = 8
    width: int | None = None
    height: int | None = None
    size: int = 0
    # what `read_dat` dropped, by decoder kind, and the byte offsets of the first few items
    skipped: dict[str, int] = field(default_factory=dict)
    skipped_offsets: list[int] = field(default_factory=list)


def read_dat(path: str | Path, *, strict: bool = False) -> tuple[DatHeader, EventArray]:
    """Read a DAT file; a trailing partial record is an error (strict) or dropped with a warning."""
    with Path(path).open("rb") as f:
        lines, _ = read_header_lines(f)
        kind = f.read(2)
        start = f.tell()
        data = f.read()
    fields: dict[str, str] = {}
    for line in lines:
        key, _, value = line[1:].strip().partition(" ")
        if key:
            fields[key] = value.strip()
    if len(kind) < 2:
        raise EvtDecodeError(
            f"{path}: DAT file ends before the event type/size bytes", offset=start, kind="truncated"
        )
    hdr = DatHeader(fields=fields, event_type=kind[0], event_size=kind[1], size=start)
    for attr, keys in (("width", ("Width", "width")), ("height", ("Height", "height"))):
        for key in keys:
            if key in fields:
                try:
                    setattr(hdr, attr, int(fields[key]))
                except ValueError:
                    raise EvtDecodeError(
                        f"{path}: DAT header {key} {fields[key]!r} is not an integer", offset=0, kind="header"
                    ) from None
    if hdr.event_size != 8:
        raise EvtDecodeError(
            f"{path}: DAT event size {hdr.event_size} at byte offset {start - 1}, expected 8",
            offset=start - 1,
            kind="unknown_type",
        )
    n = len(data) // 8
    if len(data) % 8:
        off = start + n * 8
        if strict:
            raise EvtDecodeError(
                f"{path}: truncated DAT record at byte offset {off}", offset=off, kind="truncated"
            )
        log.warning("%s: dropping %d trailing bytes of a partial DAT record", path, len(data) % 8)
        hdr.skipped[KIND_NAMES[TRUNCATED]] = 1
        hdr.skipped_offsets.append(off)
    rec = np.frombuffer(data, _RECORD, count=n)
    bad = _out_of_order(rec["t"])
    if bad.size:
        off = start + int(bad[0]) * 8
        if strict:
            raise EvtDecodeError(
                f"{path}: non_monotonic_time: DAT record earlier than the one before it at byte offset {off}",
                offset=off,
                kind=KIND_NAMES[NON_MONOTONIC_TIME],
            )
        log.warning(
            "%s: dropping %d DAT records out of time order (first at byte offset %d)", path, bad.size, off
        )
        hdr.skipped[KIND_NAMES[NON_MONOTONIC_TIME]] = int(bad.size)
        hdr.skipped_offsets = sorted([*hdr.skipped_offsets, *(start + bad[:MAX_SKIP_OFFSETS] * 8).tolist()])[
            :MAX_SKIP_OFFSETS
        ]
        rec = np.delete(rec, bad)
    d = rec["d"]
    x = (d & 0x3FFF).astype(np.uint16)
    y = ((d >> 14) & 0x3FFF).astype(np.uint16)
    p = np.where((d >> 28) != 0, 1, -1).astype(np.int8)
    return hdr, EventArray(x, y, p, rec["t"].astype(np.int64))


def _out_of_order(t: NDArray[np.uint32]) -> NDArray[np.intp]:
    """Indices of the records to drop so that the rest is time-sorted: a lone record above both
    its successor and its predecessor's successor level (a spike ahead), then every record below
    the running maximum of the others."""
    if t.size < 2:
        return np.empty(0, np.intp)
    t64 = t.astype(np.int64)
    prev = np.r_[np.int64(-1), t64[:-2]]  # t[i - 1] for i in 0 .. n - 2
    spike = np.zeros(t.size, bool)
    spike[:-1] = (t64[:-1] > t64[1:]) & (prev <= t64[1:])
    kept = np.where(spike, np.int64(-1), t64)
    behind = t64 < np.maximum.accumulate(kept)
    return np.flatnonzero(spike | behind)


def write_dat(
    path: str | Path,
    events: EventArray,
    *,
    width: int | None = None,
    height: int | None = None,
    fields: dict[str, str] | None = None,
) -> None:
    """Write CD events as a DAT file (t must fit in u32, x/y in 14 bits)."""
    if len(events):
        if int(events.t.min()) < 0 or int(events.t.max()) > 0xFFFFFFFF:
            raise EventDataError("DAT stores time as u32 microseconds; event time out of range")
        if int(events.x.max()) > 0x3FFF or int(events.y.max()) > 0x3FFF:
            raise EventDataError("DAT stores x/y in 14 bits; event coordinate out of range")
    lines = ["% Data file containing Event2D events.", "% Version 2"]
    if width is not None and height is not None:
        lines += [f"% Width {width}", f"% Height {height}"]
    lines += [f"% {k} {v}" for k, v in (fields or {}).items()]
    rec = np.empty(len(events), _RECORD)
    rec["t"] = events.t.astype(np.uint32)
    pol = (events.p > 0).astype(np.uint32)
    rec["d"] = events.x.astype(np.uint32) | (events.y.astype(np.uint32) << 14) | (pol << 28)
    with Path(path).open("wb") as f:
        f.write(("\n".join(lines) + "\n").encode("ascii"))
        f.write(bytes([CD_EVENT_TYPE, 8]))
        f.write(rec.tobytes())
