"""Finalize: rewrite every stored device time as rig time, in place, so that no time is ever
mapped twice however the process dies.

The plan (clock maps and t_offset) is stored before the first time changes; event times are
then rewritten block by block through a redo log (`finalize_scratch`) and a progress attr
(`t_rig_upto`), so a finalize cut short is continued with the same plan and yields exactly
the times an uninterrupted one would. Memory stays constant however long the take is.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import h5py
import numpy as np
from numpy.typing import NDArray

from rigd.core.errors import TakeError, TakeFormatError
from rigd.core.layout import SYNC_GROUP, Events, Frames, Root, Status, Sync, TimeDomain, TriggerEdges
from rigd.core.schema import SyncReport
from rigd.core.timebase import ClockMap
from rigd.take.evt_read import EvtWordsEvents, clock_map_json
from rigd.take.h5file import utc_now

if TYPE_CHECKING:
    from rigd.take.event_store import EventStore
    from rigd.take.evt_sink import EvtWordsSink
    from rigd.take.sinks import CameraSink, EventSink

log = logging.getLogger(__name__)

#: Events rewritten per finalize block (rounded down to whole chunks): bounds memory and is
#: the unit of the redo log, so a crash costs at most one block of redone work.
_FINALIZE_BLOCK = 1 << 20
#: ms_to_idx entries computed per step (bounds memory on sparse, long takes).
_MS_STEP = 1 << 20

#: A column's rewrite in one finalize block: [(start, stop) segments], their rows concatenated.
_Segments = tuple[list[tuple[int, int]], NDArray[Any]]


def _crash_point(stage: str, sensor: str, start: int) -> None:
    """No-op seam between the steps of a finalize block; tests replace it to simulate a crash."""


@dataclass(frozen=True, slots=True)
class FinalizePlan:
    """What finalize maps with, stored before the first time is rewritten (see resume)."""

    t_offset: int
    source: str
    maps: dict[str, ClockMap]

    def to_json(self) -> str:
        maps = {name: [m.device_ref_us, m.rig_ref_us, m.rate, m.frac_us] for name, m in self.maps.items()}
        # json writes floats with repr(): they read back bit-exact.
        return json.dumps({"t_offset": self.t_offset, "t_offset_source": self.source, "maps": maps})

    @classmethod
    def from_json(cls, text: str, where: str) -> FinalizePlan:
        try:
            data = json.loads(text)
            maps = {
                str(name): ClockMap(int(v[0]), int(v[1]), float(v[2]), float(v[3]))
                for name, v in data["maps"].items()
            }
            return cls(int(data["t_offset"]), str(data["t_offset_source"]), maps)
        except (json.JSONDecodeError, KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
            raise TakeFormatError(f"{where}: /: attr {Root.FINALIZE_PLAN} does not parse: {exc}") from exc


def _store_segments(ds: h5py.Dataset, segments: list[tuple[int, int]], rows: NDArray[Any]) -> None:
    pos = 0
    for a, b in segments:
        ds[a:b] = rows[pos : pos + b - a]
        pos += b - a


class Finalizer:
    """Finalizes the sinks of one open take; the writer checks its state before calling."""

    def __init__(
        self,
        f: h5py.File,
        path: Path,
        events: Mapping[str, EventStore],
        cameras: Mapping[str, CameraSink],
        *,
        event_opts: Mapping[str, Any],
        small_opts: Mapping[str, Any],
    ) -> None:
        self._f = f
        self._path = path
        self._events = events
        self._cameras = cameras
        self._event_opts = event_opts
        self._small_opts = small_opts

    def plan(
        self,
        maps: Mapping[str, ClockMap],
        frame_pulse_index: Mapping[str, NDArray[np.int64]],
        report: SyncReport,
    ) -> FinalizePlan:
        """Check the inputs cover every device and choose the one t_offset for all sensors."""
        where = str(self._path)
        for name in (*self._cameras, *self._events):
            if name not in maps:
                raise TakeError(f"{where}: finalize: no clock map for device {name!r}")
        for name, idx in frame_pulse_index.items():
            if name not in self._cameras:
                raise TakeError(f"{where}: finalize: frame_pulse_index names unknown camera {name!r}")
            if np.asarray(idx).shape != (self._cameras[name].n_frames,):
                raise TakeError(
                    f"{where}: finalize: frame_pulse_index[{name!r}] has shape {np.asarray(idx).shape}, "
                    f"expected ({self._cameras[name].n_frames},) (frames written)"
                )
        t_offset, source = self._choose_t_offset(maps, report)
        return FinalizePlan(t_offset, source, dict(maps))

    def _choose_t_offset(self, maps: Mapping[str, ClockMap], report: SyncReport) -> tuple[int, str]:
        """One offset for all sensors: the first pulse, else the earliest event, else 0."""
        if report.t_first_pulse_us is not None:
            return int(report.t_first_pulse_us), "first_pulse"
        firsts = [
            int(maps[name].to_rig(np.asarray([t], np.int64))[0])
            for name, sink in self._events.items()
            if sink.n_written and (t := sink.first_time()) is not None
        ]
        return (min(firsts), "first_event") if firsts else (0, "none")

    def start(
        self, plan: FinalizePlan, frame_pulse_index: Mapping[str, NDArray[np.int64]], report: SyncReport
    ) -> None:
        """Write what does not touch a device time, then store the plan: from here on a crash
        leaves a take `rigd.take.resume.resume_take` continues with `run`."""
        f = self._f
        for name, idx in frame_pulse_index.items():
            self._cameras[name].series[Frames.PULSE_INDEX][...] = np.asarray(idx, dtype=np.int64)
        # The reader of the report must not mistake an empty device for a lost file; the
        # caller's report gains the notes too, so what it shows is what the take holds.
        report.warnings.extend(n for n in self.empty_device_notes() if n not in report.warnings)
        self.write_sync(plan.maps, report)
        for sink in self._events.values():
            sink.group.attrs[Events.FINALIZE_UPTO] = np.int64(0)
        f.attrs[Root.FINALIZE_PLAN] = plan.to_json()
        # If the process dies while times are being rewritten, this says so (see the docs).
        f.attrs[Root.FINALIZE_STARTED_UTC] = utc_now()
        f.flush()

    def empty_device_notes(self) -> list[str]:
        """One sync-report line per device that recorded nothing (capped lens, unplugged from
        the start): its datasets stay empty and its clock map ties no data."""
        out = [
            f"{name}: recorded nothing (0 frames)" for name, cam in self._cameras.items() if not cam.n_frames
        ]
        for name, sink in self._events.items():
            n_trig = int(sink.trig[TriggerEdges.T_DEVICE].shape[0])
            if not sink.n_written and not n_trig:
                out.append(f"{name}: recorded nothing (0 events, 0 trigger edges)")
            elif not sink.n_written:
                out.append(f"{name}: recorded no events ({n_trig} trigger edges)")
            elif not n_trig:
                out.append(f"{name}: recorded no trigger edges ({sink.n_written} events)")
        return out

    def run(self, plan: FinalizePlan) -> None:
        """Map every time with `plan` and mark the take complete (also after a crash)."""
        f = self._f
        for name, sink in self._events.items():
            sink.finalize_times(self, plan.maps[name], plan.t_offset)
            sink.group.attrs[Events.T_OFFSET_SOURCE] = plan.source
        for name, cam in self._cameras.items():
            dev = cam.series[Frames.T_EXPOSURE_START_DEVICE][...]
            cam.series[Frames.T_EXPOSURE_START][...] = plan.maps[name].to_rig(dev)
        f.attrs[Root.TIME_DOMAIN] = TimeDomain.RIG
        f.attrs[Root.STATUS] = Status.COMPLETE
        if Root.FINALIZE_STARTED_UTC in f.attrs:
            del f.attrs[Root.FINALIZE_STARTED_UTC]
        f.attrs[Root.FINALIZED_UTC] = utc_now()
        f.flush()

    def drop_bookkeeping(self) -> None:
        """Only after "complete" is on disk: dropping t_rig_upto earlier could make a resumed
        finalize map the events a second time."""
        f = self._f
        for sink in self._events.values():
            g = sink.group
            if Events.FINALIZE_UPTO in g.attrs:
                del g.attrs[Events.FINALIZE_UPTO]
            if Events.FINALIZE_SCRATCH in g:
                del g[Events.FINALIZE_SCRATCH]
        for sink in self._events.values():
            sink.drop_tails()
        if Root.FINALIZE_PLAN in f.attrs:
            del f.attrs[Root.FINALIZE_PLAN]
        f.flush()

    def write_sync(self, maps: Mapping[str, ClockMap], report: SyncReport) -> None:
        """(Re)write /sync; replacing it is safe, it holds no recorded data."""
        sync = self._f[SYNC_GROUP]
        for key in (Sync.REPORT, Sync.DEVICES):
            if key in sync:
                del sync[key]
        sync.create_dataset(Sync.REPORT, data=report.model_dump_json(), dtype=h5py.string_dtype("utf-8"))
        devs = sync.create_group(Sync.DEVICES)
        for name, cmap in maps.items():
            g = devs.create_group(name)
            g.attrs[Sync.DEVICE_REF] = np.int64(cmap.device_ref_us)
            g.attrs[Sync.RIG_REF] = np.int64(cmap.rig_ref_us)
            g.attrs[Sync.RATE] = float(cmap.rate)
            g.attrs[Sync.FRAC] = float(cmap.frac_us)
            g.attrs[Sync.DRIFT_PPM] = float(cmap.drift_ppm)
            dev = report.devices.get(name)
            if dev is not None:
                g.attrs[Sync.RESIDUAL_RMS] = dev.residual_rms_us
                g.attrs[Sync.RESIDUAL_MAX] = dev.residual_max_us
                g.create_dataset(Sync.MISSING_PULSES, data=np.asarray(dev.missing_pulses, dtype=np.int64))
                g.create_dataset(Sync.DROPPED_FRAMES, data=np.asarray(dev.dropped_frames, dtype=np.int64))

    # -- event times -------------------------------------------------------------------
    def finalize_words(self, sink: EvtWordsSink, cmap: ClockMap, t_offset: int) -> None:
        """Store the clock map and the take window beside the words (their times are not
        rewritten: readers apply them) and the exact count of events inside the window, for
        which only the blocks across the window's edges are decoded. Idempotent."""
        g = sink.group
        for key in (Events.FIRST_IN_WINDOW, Events.EVENTS_IN_WINDOW):
            if key in g.attrs:
                del g.attrs[key]
        attrs = self._f.attrs
        lo, hi = (int(attrs[k]) if k in attrs else None for k in (Root.WINDOW_START, Root.WINDOW_END))
        g.attrs[Events.CLOCK_MAP] = clock_map_json(cmap)
        g.attrs[Events.WINDOW] = json.dumps([lo, hi])
        i0, i1 = EvtWordsEvents(g, self._path, cmap, (lo, hi)).window_range()
        g[Events.T_OFFSET][()] = np.int64(t_offset)
        g.attrs[Events.FIRST_IN_WINDOW] = np.int64(i0)
        g.attrs[Events.EVENTS_IN_WINDOW] = np.int64(i1 - i0)
        self._note_stored_outside(sink, i0, sink.n_written - i1)
        sink.trig[TriggerEdges.T][...] = cmap.to_rig(sink.trig[TriggerEdges.T_DEVICE][...])

    def _note_stored_outside(self, sink: EvtWordsSink, before: int, after: int) -> None:
        """Events stored but outside the window (packets are kept whole, and the capture's gate
        judged by its live estimate of the clock; the final map decides) go into the take's
        `window_outside_json` as `stored_before` / `stored_after`, so that what the sensor sent
        adds up: in the window + outside + lost. Set, not added: a resumed finalize repeats it."""
        attrs = self._f.attrs
        outside = json.loads(attrs[Root.WINDOW_OUTSIDE]) if Root.WINDOW_OUTSIDE in attrs else {}
        entry = outside.setdefault(sink.name, {})
        entry["stored_before"], entry["stored_after"] = int(before), int(after)
        attrs[Root.WINDOW_OUTSIDE] = json.dumps(outside, sort_keys=True)

    def finalize_columns(self, sink: EventSink, cmap: ClockMap, t_offset: int) -> None:
        """Rewrite t as rig time - t_offset block by block and build ms_to_idx on the way.

        Events [0, t_rig_upto) are already rewritten (a resumed finalize): they are only read
        for ms_to_idx. A block logged in the scratch dataset but not confirmed is copied from
        there, never mapped again from a `t` the crash may have left half rewritten.
        """
        g = sink.group
        n = sink.n_written
        upto = min(int(g.attrs.get(Events.FINALIZE_UPTO, 0)), n)
        upto = self._redo_logged_block(sink, upto)
        n_ms = _ms_count(sink, cmap, t_offset, upto)
        ms_ds = self._new_ms_to_idx(g, n_ms)
        ms_next = 0
        for pos, rel in self._rig_time_blocks(sink, cmap, t_offset, upto):
            ms_next = _fill_ms_to_idx(ms_ds, rel, pos, ms_next, n_ms)
        g[Events.T_OFFSET][()] = np.int64(t_offset)
        trig_dev = sink.trig[TriggerEdges.T_DEVICE][...]
        sink.trig[TriggerEdges.T][...] = cmap.to_rig(trig_dev)

    def _new_ms_to_idx(self, g: h5py.Group, n_ms: int) -> h5py.Dataset:
        if Events.MS_TO_IDX in g:
            # Derived: rebuilt whole, so no chunk a crashed finalize left behind is ever read.
            del g[Events.MS_TO_IDX]
        return g.create_dataset(
            Events.MS_TO_IDX,
            shape=(n_ms,),
            # Resizable so a sensor that recorded nothing (n_ms = 0) still gets a chunked,
            # empty index: HDF5 refuses a fixed shape smaller than one chunk.
            maxshape=(None,),
            dtype=np.uint64,
            chunks=(min(max(n_ms, 1), 1 << 16),),
            **self._small_opts,
        )

    def _rig_time_blocks(
        self, sink: EventSink, cmap: ClockMap, t_offset: int, upto: int
    ) -> Iterator[tuple[int, NDArray[np.int64]]]:
        """(start, t - t_offset in rig time) per block: read where already rewritten, else
        mapped and rewritten through the redo log before it is yielded."""
        tds = sink.ds[Events.T]
        n = sink.n_written
        block = max(sink.chunk, _FINALIZE_BLOCK // sink.chunk * sink.chunk)
        pos = 0
        while pos < n:
            if pos < upto:
                stop = min(pos + block, upto)
                rel: NDArray[np.int64] = np.asarray(tds[pos:stop], dtype=np.int64)
            else:
                stop = min(pos + block, n)
                rel = cmap.to_rig(tds[pos:stop]) - t_offset
                self._rewrite_block(sink, pos, stop, {Events.T: ([(pos, stop)], rel)})
            yield pos, rel
            pos = stop

    # -- redo log ----------------------------------------------------------------------
    def _rewrite_block(self, sink: EventSink, start: int, stop: int, writes: dict[str, _Segments]) -> None:
        """Redo-logged in-place rewrite of one block: log, mark, write, confirm.

        `writes`: per column, the rows to store at its segments (t: the mapped block; x, y, p:
        chunks still stored raw, recompressed). Each step is flushed before the next, so
        whatever a kill leaves on disk is the old block with a stale log, a complete log to
        copy from, or the confirmed new block: nothing is ever mapped twice.
        """
        g = sink.group
        log_g = g.get(Events.FINALIZE_SCRATCH)
        if log_g is None:
            log_g = g.create_group(Events.FINALIZE_SCRATCH)
        for key in list(log_g):
            if key not in writes:
                del log_g[key]
        for key, (segments, rows) in writes.items():
            self._log_rows(log_g, key, segments, rows)
        _crash_point("scratch_written", sink.name, start)
        self._f.flush()
        log_g.attrs.modify(Events.SCRATCH_RANGE, np.array([start, stop], dtype=np.int64))
        self._f.flush()
        _crash_point("scratch_logged", sink.name, start)
        for key, (segments, rows) in writes.items():
            _store_segments(sink.ds[key], segments, rows)
        _crash_point("t_written", sink.name, start)
        g.attrs.modify(Events.FINALIZE_UPTO, np.int64(stop))
        self._f.flush()

    def _log_rows(
        self, log_g: h5py.Group, key: str, segments: list[tuple[int, int]], rows: NDArray[Any]
    ) -> None:
        ds = log_g.get(key)
        if ds is None:
            # Compressed like the events: a rewritten log moves, but the log that is
            # current on disk is never freed before the block it covers is confirmed.
            ds = log_g.create_dataset(
                key,
                shape=(rows.shape[0],),
                maxshape=(None,),
                dtype=rows.dtype,
                chunks=(max(1, min(rows.shape[0], 1 << 20)),),
                **self._event_opts,
            )
        else:
            ds.resize((rows.shape[0],))
        ds[...] = rows
        ds.attrs[Events.SCRATCH_SEGMENTS] = np.asarray(segments, dtype=np.int64).reshape(-1, 2)

    def _redo_logged_block(self, sink: EventSink, upto: int) -> int:
        """Copy a logged, unconfirmed block from the redo log; returns the new t_rig_upto."""
        g = sink.group
        log_g = g.get(Events.FINALIZE_SCRATCH)
        if not isinstance(log_g, h5py.Group) or Events.SCRATCH_RANGE not in log_g.attrs:
            return upto
        lo, hi = (int(v) for v in log_g.attrs[Events.SCRATCH_RANGE])
        if not (lo == upto and upto < hi <= sink.n_written):
            return upto  # stale: that block was confirmed
        log.info("take %s: %s: redoing finalize block [%d, %d) from its log", self._path, sink.name, lo, hi)
        for key, ds in log_g.items():
            segments = [
                (int(a), int(b)) for a, b in np.asarray(ds.attrs[Events.SCRATCH_SEGMENTS]).reshape(-1, 2)
            ]
            _store_segments(sink.ds[key], segments, np.asarray(ds[...]))
        g.attrs.modify(Events.FINALIZE_UPTO, np.int64(hi))
        self._f.flush()
        return hi


def _ms_count(sink: EventSink, cmap: ClockMap, t_offset: int, upto: int) -> int:
    """Length of ms_to_idx: one entry per ms up to the last event's rig time."""
    n = sink.n_written
    tds = sink.ds[Events.T]
    if n == 0:
        last_rel = -1
    elif upto >= n:
        last_rel = int(tds[n - 1])
    else:
        last_rel = int(cmap.to_rig(tds[n - 1 : n])[0]) - t_offset
    return last_rel // 1000 + 1 if last_rel >= 0 else 0


def _fill_ms_to_idx(ms_ds: h5py.Dataset, rel: NDArray[np.int64], pos: int, ms_next: int, n_ms: int) -> int:
    """Store ms_to_idx entries the block starting at event `pos` settles; returns the next
    entry to fill (DSEC: the first event at or after each whole ms)."""
    ms_hi = min(int(rel[-1]) // 1000 + 1, n_ms) if rel[-1] >= 0 else 0
    while ms_next < ms_hi:
        step_hi = min(ms_next + _MS_STEP, ms_hi)
        thresholds = np.arange(ms_next, step_hi, dtype=np.int64) * 1000
        ms_ds[ms_next:step_hi] = (np.searchsorted(rel, thresholds, side="left") + pos).astype(np.uint64)
        ms_next = step_hi
    return ms_next
