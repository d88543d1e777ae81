"""Crash repair: find (and trim) what a writer killed between flushes left half-written.

A kill can stop the writer between the column appends of one flush, or after HDF5 extended
a dataset but before its new chunks reached the file, or while a truncated file (a failed
write) still names chunks past its real end. Every group is cut back to the rows all of its
datasets really hold; each cut is reported as a `Trim` with the items of real data it lost,
so nothing is ever dropped silently.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict

from rigd.core.errors import TakeFormatError
from rigd.core.layout import (
    EVENT_DTYPES,
    EVENTS_GROUP,
    FRAME_SERIES,
    FRAMES_GROUP,
    PULSE_SERIES,
    PULSES_PATH,
    TRIGGER_DTYPES,
    Events,
    Frames,
    Root,
    TriggerEdges,
)
from rigd.core.schema import SCHEMA_VERSION, LossKind, has_item
from rigd.take.evt_read import is_evt_words
from rigd.take.evt_repair import apply_evt_cut, plan_evt_cut
from rigd.take.h5file import TRUNCATED_EOF_ATTR, append_rows, attr_text, require_dataset, require_group
from rigd.take.tails import tail_end, tail_rows

log = logging.getLogger(__name__)

#: Rows read per step when scanning a column for a damaged tail (bounds memory).
_SCAN_BLOCK = 1 << 20


class Trim(BaseModel):
    """One group of datasets cut back by `check_repair`: what, from which lengths, and why."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    hpath: str
    """HDF5 path of the group whose datasets were trimmed, e.g. `/events/ev0/trigger`."""
    lengths_before: dict[str, int]
    after: int
    reason: str
    device: str
    what: LossKind
    lost: int
    """Items that were real data (a LossRecord count); preallocated empty frames are not."""


def check_repair(
    f: h5py.File, path: Path, *, apply: bool, check_order: bool = True, data_end: int | None = None
) -> list[Trim]:
    """Find (and with `apply`, trim) what a writer killed between flushes left half-written.

    Per group, every dataset is cut to the length all of them really hold: event columns to
    their common stored length and before a non-monotonic tail of `t` (the writer only ever
    stores non-decreasing t, so a decrease is damage); camera images to the flushed timestamp
    series (the rest is preallocation or frames whose timestamps were lost); trigger-in and
    pulse columns to their common stored length; and everywhere a zero-filled tail a stale chunk
    leaves (see `_stale_tail`). Nothing is ever cut silently: each cut is a
    `Trim`, with how many items of real data it lost. `check_order=False` skips the scan of
    `t` (a finalize in progress has rewritten part of it). `data_end`: where a truncated file
    really ends (default: the `truncated_eof` attr resume leaves on an extended one).
    """
    scan = _Scan(str(path), apply=apply, check_order=check_order, data_end=data_end)
    try:
        _repair_take(f, scan)
    except (OSError, RuntimeError) as exc:
        raise TakeFormatError(f"{path}: {scan.at}: cannot be read: {exc}") from exc
    for t in scan.trims:
        log.warning(
            "take %s: %s trimmed to %d (%s; %d item(s) of data lost)%s",
            path,
            t.hpath,
            t.after,
            t.reason,
            t.lost,
            "" if apply else " [dry run]",
        )
    return scan.trims


@dataclass(slots=True)
class _Scan:
    """One check_repair pass: its options, the trims found so far, and the group being read
    (named in the message of a read error)."""

    where: str
    apply: bool
    check_order: bool
    data_end: int | None
    version: str = SCHEMA_VERSION
    trims: list[Trim] = field(default_factory=list)
    at: str = "/"

    def trim(
        self,
        group: h5py.Group,
        dsets: Mapping[str, h5py.Dataset],
        keep: int,
        reasons: list[str],
        device: str,
        what: LossKind,
        lost: int,
    ) -> None:
        """Record (and with `apply`, do) cutting every dataset of `group` to `keep` rows."""
        lengths = {k: int(d.shape[0]) for k, d in dsets.items()}
        if all(v == keep for v in lengths.values()):
            return
        reason = "; ".join(reasons) or "datasets of unequal length"
        self.trims.append(
            Trim(
                hpath=group.name,
                lengths_before=lengths,
                after=keep,
                reason=reason,
                device=device,
                what=what,
                lost=lost,
            )
        )
        if self.apply:
            for d in dsets.values():
                if d.shape[0] != keep:
                    try:
                        d.resize((keep, *d.shape[1:]))
                    except (OSError, RuntimeError, ValueError) as exc:
                        raise TakeFormatError(
                            f"{d.file.filename}: {d.name}: cannot be trimmed: {exc}"
                        ) from exc


def _repair_take(f: h5py.File, scan: _Scan) -> None:
    if scan.data_end is None and TRUNCATED_EOF_ATTR in f.attrs:
        scan.data_end = int(f.attrs[TRUNCATED_EOF_ATTR])
    scan.version = attr_text(f.attrs.get(Root.SCHEMA_VERSION, SCHEMA_VERSION))
    for name, g in require_group(f, EVENTS_GROUP, scan.where).items():
        scan.at = f"/{EVENTS_GROUP}/{name}"
        _require_readable_group(scan, g)
        if is_evt_words(g):
            _repair_evt_words(scan, name, g)
        else:
            cols, longest, keep = _repair_event_columns(scan, name, g)
            _merge_event_tail(scan, name, g, cols, longest, keep)
        _repair_trigger_in(scan, name, require_group(g, Events.TRIGGER, scan.where))
    for name, g in require_group(f, FRAMES_GROUP, scan.where).items():
        scan.at = f"/{FRAMES_GROUP}/{name}"
        _require_readable_group(scan, g)
        _repair_camera(scan, name, g)
    _repair_pulses(scan, require_group(f, PULSES_PATH, scan.where))


def _require_readable_group(scan: _Scan, g: h5py.Group | None) -> None:
    """h5py lists a link whose object cannot be opened as None (a group whose header never
    reached the disk); say so instead of failing on its first use."""
    if not isinstance(g, h5py.Group):
        raise TakeFormatError(
            f"{scan.where}: {scan.at}: listed but cannot be opened as a group "
            "(its header never reached the file: disk full before the first flush?)"
        )


def _repair_event_columns(scan: _Scan, name: str, g: h5py.Group) -> tuple[dict[str, h5py.Dataset], int, int]:
    """x, y, p, t cut to their common stored length and before any decrease of t; returns the
    columns, their longest length before and the rows kept."""
    cols = {k: require_dataset(g, k, scan.where) for k in EVENT_DTYPES}
    longest = max(int(d.shape[0]) for d in cols.values())
    stored = {k: stored_prefix(d, scan.data_end) for k, d in cols.items()}
    keep = min(stored.values())
    reasons = []
    if len({int(d.shape[0]) for d in cols.values()}) > 1:
        reasons.append("x/y/p/t of unequal length (killed between column appends)")
    if any(stored[k] < int(cols[k].shape[0]) for k in cols):
        reasons.append("chunks past the end never reached the file")
    bad = _first_decrease(cols[Events.T], keep) if scan.check_order else None
    if bad is not None:
        reasons.append(f"t decreases at index {bad} (damaged tail)")
        keep = bad
    scan.trim(g, cols, keep, reasons, name, "events", longest - keep)
    return cols, longest, keep


def _repair_evt_words(scan: _Scan, name: str, g: h5py.Group) -> None:
    """EVT words and their index cut to what both really hold (see `rigd.take.evt_repair`)."""
    words = require_dataset(g, Events.EVT_WORDS, scan.where)
    index = require_dataset(g, Events.EVT_INDEX, scan.where)
    finalizing = not scan.check_order
    cut = plan_evt_cut(
        g, stored_prefix(words, scan.data_end), stored_prefix(index, scan.data_end), finalizing=finalizing
    )
    if cut.reasons:
        scan.trims.append(
            Trim(
                hpath=g.name,
                lengths_before={Events.EVT_INDEX: cut.rows_before, Events.EVT_WORDS: cut.bytes_stored},
                after=cut.rows_kept,
                reason="; ".join(cut.reasons),
                device=name,
                what="events",
                lost=cut.events_lost,
            )
        )
    if scan.apply and not finalizing:
        apply_evt_cut(g, cut)


def _merge_event_tail(
    scan: _Scan, name: str, g: h5py.Group, cols: Mapping[str, h5py.Dataset], longest: int, keep: int
) -> None:
    """Append the flushed tail slot that continues the kept events (see `rigd.take.tails`);
    report the rows a slot claims beyond them as lost."""
    slot, m = tail_rows(g, keep) if scan.check_order else (0, 0)
    claimed = tail_end(g)
    beyond = claimed - max(longest, keep + m)
    if beyond > 0:
        scan.trims.append(
            Trim(
                hpath=f"{g.name}/{Events.TAIL_PREFIX}t",
                lengths_before={"rows_claimed": claimed},
                after=keep + m,
                reason="flushed tail events that do not continue the main datasets (gap or damage)",
                device=name,
                what="events",
                lost=beyond,
            )
        )
    if scan.apply and m:
        for key, d in cols.items():  # a new chunk: appended, nothing rewritten
            append_rows(d, keep, np.asarray(g[f"{Events.TAIL_PREFIX}{key}"][slot, :m]))


def _repair_trigger_in(scan: _Scan, name: str, tg: h5py.Group) -> None:
    """An event sensor's trigger-in columns cut to the rows all of them hold."""
    scan.at = tg.name
    # host_time_ns is required from schema 1.1 on and used whenever present.
    keys = [
        k
        for k in TRIGGER_DTYPES
        if k != TriggerEdges.HOST_TIME_NS or k in tg or has_item(scan.version, f"{Events.TRIGGER}/{k}")
    ]
    trig = {k: require_dataset(tg, k, scan.where) for k in keys}
    nonzero = (
        (TriggerEdges.T_DEVICE, TriggerEdges.HOST_TIME_NS)
        if TriggerEdges.HOST_TIME_NS in trig
        else (TriggerEdges.T_DEVICE,)
    )
    order = (TriggerEdges.T, TriggerEdges.T_DEVICE) if scan.check_order else None
    longest, keep, reasons = _columns_keep(trig, scan.data_end, nonzero, order, "trigger")
    scan.trim(tg, trig, keep, reasons, name, "triggers", longest - keep)


def _repair_camera(scan: _Scan, name: str, g: h5py.Group) -> None:
    """Timestamp series cut to their common stored length, images to the frames they time."""
    series = {k: require_dataset(g, k, scan.where) for k in FRAME_SERIES}
    images = require_dataset(g, Frames.IMAGES, scan.where)
    n_series = max(int(d.shape[0]) for d in series.values())
    stored = min(stored_prefix(d, scan.data_end) for d in series.values())
    reasons = []
    if stored < n_series:
        reasons.append("timestamp series of unequal or unwritten length")
    keep = _stale_tail(
        series,
        stored,
        (Frames.T_EXPOSURE_START_DEVICE, Frames.HOST_TIME_NS),
        (Frames.T_EXPOSURE_START, Frames.T_EXPOSURE_START_DEVICE) if scan.check_order else None,
    )
    if keep < stored:
        reasons.append("zero-filled tail of the timestamp series (a chunk the flush did not update)")
    img_stored = stored_prefix(images, scan.data_end)
    if img_stored < keep:
        reasons.append("images past the end never reached the file")
        keep = img_stored
    if int(images.shape[0]) > keep:
        reasons.append(f"images beyond the {keep} flushed timestamps (preallocation, frames not flushed)")
    # Frames beyond `keep` whose image was stored are real frames that lost their timestamps.
    stored_imgs = _allocated_chunks(images, scan.data_end)
    lost = max(n_series - keep, int((stored_imgs >= keep).sum()))
    scan.trim(g, {Frames.IMAGES: images, **series}, keep, reasons, name, "frames", lost)


def _repair_pulses(scan: _Scan, pulses: h5py.Group) -> None:
    """The trigger box pulse columns cut to the rows all of them hold."""
    scan.at = pulses.name
    cols = {k: require_dataset(pulses, k, scan.where) for k in PULSE_SERIES}
    longest, keep, reasons = _columns_keep(cols, scan.data_end, PULSE_SERIES, None, "pulse")
    scan.trim(pulses, cols, keep, reasons, "trigger", "pulses", longest - keep)


def stored_prefix(ds: h5py.Dataset, data_end: int | None = None) -> int:
    """Leading entries of a chunked dataset whose chunks were all written.

    Its extent can run ahead of its chunks when a kill interrupted a flush: entries past the
    first missing chunk would silently read as the fill value (zeros). With `data_end` (the
    real end of a truncated file) a chunk stored past it counts as missing too.
    """
    n = int(ds.shape[0]) if ds.shape else 0
    if n == 0 or ds.chunks is None:
        return n
    step = int(ds.chunks[0])
    have = np.zeros(-(-n // step), dtype=bool)
    offsets = _allocated_chunks(ds, data_end) // step
    have[offsets[offsets < have.size]] = True
    missing = np.flatnonzero(~have)
    return n if missing.size == 0 else int(missing[0]) * step


def _columns_keep(
    cols: Mapping[str, h5py.Dataset],
    data_end: int | None,
    nonzero: tuple[str, ...],
    order: tuple[str, str] | None,
    what: str,
) -> tuple[int, int, list[str]]:
    """For a group of parallel columns: their longest length, the rows to keep (stored in every
    column and not a stale zero tail) and why any are cut."""
    longest = max(int(d.shape[0]) for d in cols.values())
    stored = min(stored_prefix(d, data_end) for d in cols.values())
    keep = _stale_tail(cols, stored, nonzero, order)
    reasons = [f"{what} columns of unequal or unwritten length"] if stored < longest else []
    if keep < stored:
        reasons.append("zero-filled tail (a chunk the interrupted flush did not update)")
    return longest, keep, reasons


def _stale_tail(
    dsets: Mapping[str, h5py.Dataset], n: int, nonzero: tuple[str, ...], same: tuple[str, str] | None
) -> int:
    """Rows [0, n) less a tail that a chunk the interrupted flush did not update reads as 0.

    Columns are append-only, so such a chunk (its B-tree entry still names the previous
    version while the extent already covers the new rows) reads as the correct prefix followed
    by the fill value 0. `nonzero` columns never hold 0 after a nonzero value in real data
    (host times, device clocks); a column that is all zeros says nothing and is skipped.
    `same`: two columns the writer stores identical while recording (t and its device copy).
    """
    keep = n
    for key in nonzero:
        last = _last_nonzero(dsets[key], keep)
        if last > 0:
            keep = last
    if same is not None:
        keep = _first_mismatch(dsets[same[0]], dsets[same[1]], keep)
    return keep


def _last_nonzero(ds: h5py.Dataset, n: int) -> int:
    """1 + index of the last nonzero entry in ds[:n] (0 if none), scanning back in blocks."""
    hi = n
    while hi > 0:
        lo = max(0, hi - _SCAN_BLOCK)
        hit = np.flatnonzero(np.asarray(ds[lo:hi]) != 0)
        if hit.size:
            return lo + int(hit[-1]) + 1
        hi = lo
    return 0


def _first_mismatch(a: h5py.Dataset, b: h5py.Dataset, n: int) -> int:
    """First index i < n with a[i] != b[i], else n (forward, in blocks)."""
    for lo in range(0, n, _SCAN_BLOCK):
        hi = min(lo + _SCAN_BLOCK, n)
        bad = np.flatnonzero(np.asarray(a[lo:hi]) != np.asarray(b[lo:hi]))
        if bad.size:
            return lo + int(bad[0])
    return n


def _first_decrease(ds: h5py.Dataset, n: int) -> int | None:
    """First index i < n with ds[i] < ds[i-1], scanning in blocks (constant memory)."""
    prev: int | None = None
    for start in range(0, n, _SCAN_BLOCK):
        t = np.asarray(ds[start : min(start + _SCAN_BLOCK, n)], dtype=np.int64)
        if prev is not None and int(t[0]) < prev:
            return start
        bad = np.flatnonzero(t[1:] < t[:-1])
        if bad.size:
            return start + int(bad[0]) + 1
        prev = int(t[-1])
    return None


def _allocated_chunks(ds: h5py.Dataset, data_end: int | None) -> NDArray[np.int64]:
    """First-axis offsets of the chunks that hold data (within the file's real end)."""
    if ds.chunks is None or not ds.shape or ds.shape[0] == 0:
        return np.empty(0, np.int64)
    offsets: list[int] = []

    def seen(info: Any) -> None:
        if data_end is None or int(info.byte_offset) + int(info.size) <= data_end:
            offsets.append(int(info.chunk_offset[0]))

    _chunk_iter(ds, seen)
    return np.asarray(offsets, dtype=np.int64)


def _chunk_iter(ds: h5py.Dataset, fn: Callable[[Any], None]) -> None:
    """Call fn(StoreInfo) for every allocated chunk; one pass (H5Dchunk_iter, HDF5 >= 1.14)."""
    dsid = ds.id
    if hasattr(dsid, "chunk_iter"):
        dsid.chunk_iter(fn)
        return
    for i in range(dsid.get_num_chunks()):  # older HDF5: slower, same answer
        fn(dsid.get_chunk_info(i))
