"""Read-only access to take files for training jobs.

`Take` holds the file open and answers what is take-wide (metadata, sync report, pulses,
summary); each device's data is a series of its own, asked for by the device's name:
`take.camera(name)` a `FrameSeries`, `take.sensor(name)` an `EventSeries` (time windows through
the DSEC `ms_to_idx` index, with the sensor's datasets held open for the Take's life:
rigd/take/event_series.py). A series gets what it needs of the take (`OpenTake`) when made,
and never calls back into the Take.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType
from typing import Any, Self

import h5py
import hdf5plugin  # noqa: F401  (registers the LZ4 / Zstd filters with h5py)
import numpy as np
from numpy.typing import NDArray
from pydantic import ValidationError

from rigd.core.devices import PulseBatch
from rigd.core.errors import TakeError, TakeFormatError
from rigd.core.layout import (
    EVENT_DTYPES,
    EVENTS_GROUP,
    EVT_INDEX_COLUMNS,
    FRAME_SERIES,
    FRAMES_GROUP,
    PULSE_SERIES,
    PULSES_PATH,
    SYNC_GROUP,
    SYNC_REPORT_PATH,
    TRIGGER_DTYPES,
    TRIGGER_GROUP,
    Device,
    Events,
    Frames,
    Pulses,
    Root,
    TimeDomain,
)
from rigd.core.schema import SCHEMA_NAME, SCHEMA_VERSION, SyncReport, decode_journal, has_item
from rigd.take.calibration import read_board_pose, read_calibration
from rigd.take.event_series import EventSeries
from rigd.take.evt_read import is_evt_words
from rigd.take.frame_series import FrameSeries
from rigd.take.guard import DAMAGE_ERRORS, OpenTake, as_format_error, format_errors
from rigd.take.h5file import attr_text
from rigd.take.linked import TakeH5
from rigd.take.manifest import PartEntry
from rigd.take.summary import CameraSummary, EventSensorSummary, TakeSummary
from rigd.take.verdict import take_verdict

log = logging.getLogger(__name__)

#: Raw-data chunk cache per open dataset (held for the Take's life, so per column and sensor):
#: keeps the chunk a sequential read shares with the next block decoded; random windows rarely
#: share one, and 16 MiB read them no faster (bench.random_windows' takes).
_CHUNK_CACHE_BYTES = 4 << 20


def _attr_str(obj: h5py.HLObject, key: str, default: str = "") -> str:
    return attr_text(obj.attrs.get(key, default))


#: Largest sensor side a take may declare (event coordinates are uint16).
_MAX_SIDE = 65535


def _schema_dtype(hpath: str) -> str | None:
    """The dtype the schema gives the dataset at `hpath` (None: checked apart or free)."""
    parts = hpath.split("/")
    name = parts[-1]
    if parts[0] == EVENTS_GROUP and len(parts) == 4 and parts[2] == Events.TRIGGER:
        return TRIGGER_DTYPES.get(name)
    if parts[0] == EVENTS_GROUP:
        other = {Events.MS_TO_IDX: "uint64", Events.T_OFFSET: "int64", Events.EVT_INDEX: "int64"}
        return EVENT_DTYPES.get(name) or other.get(name)
    if name in FRAME_SERIES or name in PULSE_SERIES:
        return "int64"
    return None


def _finite(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)


@format_errors
class Take:
    """An open take file (read-only). Use as a context manager or call close()."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        # a joined multi-host take's device groups live in its part files: `_h` resolves them
        self._h = TakeH5(self.path, "r", rdcc_nbytes=_CHUNK_CACHE_BYTES, rdcc_nslots=10007)
        self._f = self._h.file
        try:
            self._check_header()
            self._check_layout()
        except TakeError:
            self._h.close()
            raise
        except DAMAGE_ERRORS as exc:
            self._h.close()
            raise as_format_error(self.path, "its layout", exc) from exc
        except BaseException:
            self._h.close()
            raise
        self._series: dict[str, EventSeries] = {}

    def _check_header(self) -> None:
        f = self._f
        schema = _attr_str(f, Root.SCHEMA)
        if schema != SCHEMA_NAME:
            raise TakeFormatError(f"{self.path}: /: attr schema is {schema!r}, expected {SCHEMA_NAME!r}")
        major = _attr_str(f, Root.SCHEMA_VERSION).split(".")[0]
        if major != SCHEMA_VERSION.split(".")[0]:
            raise TakeFormatError(
                f"{self.path}: /: schema_version {self.schema_version!r} is not readable by this rigd "
                f"(reads {SCHEMA_VERSION.split('.')[0]}.x)"
            )

    def _required(self) -> Iterator[str]:
        """HDF5 paths every reader method relies on, for the take's version and time domain."""
        f = self._f
        version = _attr_str(f, Root.SCHEMA_VERSION, SCHEMA_VERSION)
        rig = _attr_str(f, Root.TIME_DOMAIN) == TimeDomain.RIG
        for name in self.event_sensors:
            base = f"{EVENTS_GROUP}/{name}"
            g = self._h.get(base)
            if isinstance(g, h5py.Group) and is_evt_words(g):
                yield from (f"{base}/evt_words", f"{base}/evt_index")
            else:
                yield from (f"{base}/{k}" for k in EVENT_DTYPES)
            yield f"{base}/{Events.T_OFFSET}"
            if rig and not (isinstance(g, h5py.Group) and is_evt_words(g)):
                yield f"{base}/{Events.MS_TO_IDX}"
            trig = (k for k in TRIGGER_DTYPES if has_item(version, f"{Events.TRIGGER}/{k}"))
            yield from (f"{base}/trigger/{k}" for k in trig)
        for name in self.cameras:
            yield f"{FRAMES_GROUP}/{name}/images"
            yield from (f"{FRAMES_GROUP}/{name}/{k}" for k in FRAME_SERIES)
        yield from (f"{TRIGGER_GROUP}/pulses/{k}" for k in PULSE_SERIES)

    def _check_layout(self) -> None:
        """Refuse a damaged take on open with the first missing dataset named, instead of a
        KeyError from whichever read reaches it first."""
        for name in (EVENTS_GROUP, FRAMES_GROUP):
            node = self._f.get(name)
            if node is not None and not isinstance(node, h5py.Group):
                raise TakeFormatError(f"{self.path}: /{name} is not a group")
        lengths: dict[str, dict[str, int]] = {}
        for hpath in self._required():
            ds = self._h.get(hpath)
            if not isinstance(ds, h5py.Dataset):
                raise TakeFormatError(f"{self.path}: /{hpath}: required dataset is missing (damaged take)")
            self._check_dataset(hpath, ds)
            parent, _, name = hpath.rpartition("/")
            if ds.ndim and name not in (Events.EVT_WORDS, Events.EVT_INDEX, Events.MS_TO_IDX):
                lengths.setdefault(parent, {})[name] = int(ds.shape[0])
        for parent, sizes in lengths.items():  # one row per event, frame, edge or pulse in each
            if len(set(sizes.values())) > 1:
                desc = ", ".join(f"{k}={n:,}" for k, n in sizes.items())
                raise TakeFormatError(f"{self.path}: /{parent}: datasets have unequal lengths ({desc})")
        for group, names in ((EVENTS_GROUP, self.event_sensors), (FRAMES_GROUP, self.cameras)):
            for name in names:
                self._check_geometry(f"/{group}/{name}", self._h[f"{group}/{name}"])

    def _check_dataset(self, hpath: str, ds: h5py.Dataset) -> None:
        """A required dataset's dtype and dimensions are the schema's (a float image or a 2-D
        pulse series would otherwise read as something it is not)."""
        want = _schema_dtype(hpath)
        name = hpath.rsplit("/", 1)[-1]
        ndim = {Frames.IMAGES: (3, 4), Events.EVT_INDEX: (2,), Events.T_OFFSET: (0,)}.get(name, (1,))
        where = f"{self.path}: /{hpath}"
        if ds.ndim not in ndim:
            raise TakeFormatError(
                f"{where}: has {ds.ndim} dimensions, expected {' or '.join(map(str, ndim))}"
            )
        if want is not None and ds.dtype != np.dtype(want):
            raise TakeFormatError(f"{where}: dtype {ds.dtype}, expected {np.dtype(want)}")
        if name == Frames.IMAGES and ds.dtype.kind != "u":
            raise TakeFormatError(f"{where}: dtype {ds.dtype}, expected unsigned integer pixels")
        if name == Events.EVT_INDEX and ds.shape[1] < len(EVT_INDEX_COLUMNS):
            raise TakeFormatError(
                f"{where}: has {ds.shape[1]} columns, expected at least {len(EVT_INDEX_COLUMNS)}"
            )

    def _check_geometry(self, where: str, g: h5py.Group) -> None:
        """width and height: integers a sensor can have (events store uint16 coordinates)."""
        for key in (Device.WIDTH, Device.HEIGHT):
            value = g.attrs.get(key)
            if value is None and where.startswith(f"/{FRAMES_GROUP}"):
                continue  # older cameras: the image shape says it
            if not isinstance(value, (int, np.integer)) or not 0 < int(value) <= _MAX_SIDE:
                raise TakeFormatError(
                    f"{self.path}: {where}: attribute {key} is {value!r}, expected an integer 1..{_MAX_SIDE}"
                )
        images = g.get(Frames.IMAGES)
        if isinstance(images, h5py.Dataset) and Device.WIDTH in g.attrs and Device.HEIGHT in g.attrs:
            hw = (int(g.attrs[Device.HEIGHT]), int(g.attrs[Device.WIDTH]))
            if tuple(images.shape[1:3]) != hw:
                raise TakeFormatError(
                    f"{self.path}: {where}/images: frames are {tuple(images.shape[1:3])} (H, W) but the "
                    f"camera's attributes say {hw}"
                )

    def _where_file(self) -> str:
        return str(self.path)

    # -- lifecycle ---------------------------------------------------------------------
    def close(self) -> None:
        self._series.clear()
        self._h.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- metadata ----------------------------------------------------------------------
    @property
    def status(self) -> str:
        return _attr_str(self._f, Root.STATUS)

    @property
    def schema_version(self) -> str:
        return _attr_str(self._f, Root.SCHEMA_VERSION)

    @property
    def take_id(self) -> str:
        return _attr_str(self._f, Root.TAKE_ID)

    @property
    def time_domain(self) -> str:
        return _attr_str(self._f, Root.TIME_DOMAIN)

    @property
    def config(self) -> dict[str, Any]:
        raw = self._dataset(Root.CONFIG)[()]
        text = attr_text(raw)
        return self._json_object(text, f"/{Root.CONFIG}")

    @property
    def journal(self) -> dict[str, Any] | None:
        """The loss bookkeeping of the last flush (`/journal_json`, newest readable slot), or None."""
        node = self._f.get(Root.JOURNAL)
        if not isinstance(node, h5py.Dataset):
            return None
        found = decode_journal(np.asarray(node[...]))
        return None if found is None else found[1]

    @property
    def end_reason(self) -> str | None:
        """Why the recording ended (set by the capture; None for older or converted takes)."""
        return _attr_str(self._f, Root.END_REASON) if Root.END_REASON in self._f.attrs else None

    @property
    def recovered_utc(self) -> str | None:
        """When `rigd recover` sealed this take after a crash; None for a take closed normally."""
        return _attr_str(self._f, Root.RECOVERED_UTC) if Root.RECOVERED_UTC in self._f.attrs else None

    @property
    def recovery_report(self) -> dict[str, Any] | None:
        """The RecoveryReport (as a dict) of a recovered take: what was trimmed and why."""
        if Root.RECOVERY_REPORT not in self._f.attrs:
            return None
        return self._json_object(_attr_str(self._f, Root.RECOVERY_REPORT), f"/ attr {Root.RECOVERY_REPORT}")

    @property
    def window_outside(self) -> dict[str, Any] | None:
        """Per device, what arrived outside the take window and was not written (root attr
        `window_outside_json`); None for a take without a window."""
        if Root.WINDOW_OUTSIDE not in self._f.attrs:
            return None
        return self._json_object(_attr_str(self._f, Root.WINDOW_OUTSIDE), f"/ attr {Root.WINDOW_OUTSIDE}")

    @property
    def parts(self) -> list[PartEntry] | None:
        """A multi-host take's parts manifest (host, file, devices, sha256, status of each part),
        None for a take written on one host (docs/take-format.md, "Multi-host takes")."""
        return self._h.manifest

    def _json_object(self, text: str, where: str) -> dict[str, Any]:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise TakeFormatError(f"{self.path}: {where} is not valid JSON: {exc}") from exc
        if not isinstance(data, dict):
            raise TakeFormatError(f"{self.path}: {where} is not a JSON object")
        return data

    @property
    def calibration(self) -> dict[str, dict[str, Any]] | None:
        """Calibrations stored in the take by `rigd calibrate ... --into-take`, by device."""
        return read_calibration(self._f)

    @property
    def board_pose(self) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
        """(R, t) of the board plane in the rig frame (x_rig = R x_board + t), when stored."""
        return read_board_pose(self._f)

    @property
    def sync_report(self) -> SyncReport | None:
        """The sync report, or None for a take that was never finalized."""
        node = self._f.get(SYNC_REPORT_PATH)
        if node is None:
            return None
        raw = node[()]
        text = attr_text(raw)
        try:
            return SyncReport.model_validate_json(text)
        except ValidationError as exc:
            raise TakeFormatError(f"{self.path}: /{SYNC_GROUP}/report_json does not parse: {exc}") from exc

    @property
    def cameras(self) -> list[str]:
        return sorted(self._f.get(FRAMES_GROUP, {}).keys())

    @property
    def event_sensors(self) -> list[str]:
        return sorted(self._f.get(EVENTS_GROUP, {}).keys())

    def _dataset(self, hpath: str) -> h5py.Dataset:
        node = self._f.get(hpath)
        if not isinstance(node, h5py.Dataset):
            raise TakeFormatError(f"{self.path}: /{hpath} is missing or not a dataset")
        return node

    def _check_open(self) -> None:
        """A closed file answers `get` with None: say it is closed, not that a device is missing."""
        if not self._f:
            raise TakeError(f"{self.path}: the take is closed")

    def _open_take(self) -> OpenTake:
        """What a series reads of this take (fixed while it is open read-only)."""
        return OpenTake(self.path, self.status, self.time_domain)

    def pulses(self) -> PulseBatch:
        g = self._f.get(PULSES_PATH)
        if not isinstance(g, h5py.Group):
            raise TakeFormatError(f"{self.path}: /{TRIGGER_GROUP}/pulses is missing")
        return PulseBatch(
            np.asarray(g[Pulses.INDEX][...], dtype=np.int64),
            np.asarray(g[Pulses.T_US][...], dtype=np.int64),
            np.asarray(g[Pulses.HOST_TIME_NS][...], dtype=np.int64),
        )

    def camera(self, name: str, demosaic: bool = True) -> FrameSeries:
        """One camera's frames; a Bayer camera's demosaiced to RGB unless `demosaic=False`."""
        self._check_open()
        g = self._h.get(f"{FRAMES_GROUP}/{name}")
        if not isinstance(g, h5py.Group):
            raise TakeError(f"{self.path}: no camera {name!r} (has {self.cameras})")
        return FrameSeries(self._open_take(), name, g, demosaic)

    def sensor(self, name: str) -> EventSeries:
        """One event sensor's events. The same EventSeries for the Take's life (it keeps the
        sensor's datasets open); like a FrameSeries, it reads only while the Take is open."""
        series = self._series.get(name)
        if series is None:
            self._check_open()
            g = self._h.get(f"{EVENTS_GROUP}/{name}")
            if not isinstance(g, h5py.Group):
                raise TakeError(f"{self.path}: no event sensor {name!r} (has {self.event_sensors})")
            series = self._series[name] = EventSeries(self._open_take(), name, g)
        return series

    # -- summary -----------------------------------------------------------------------
    def summary(self) -> TakeSummary:
        """Counts, rates and sync quality; reads only metadata, first/last times and the report."""
        report = self.sync_report
        devs = report.devices if report else {}
        cams: dict[str, CameraSummary] = {}
        for name in self.cameras:
            fs = self.camera(name, demosaic=False)
            ts = fs.timestamps_us
            fps = (
                (ts.size - 1) / ((int(ts[-1]) - int(ts[0])) / 1e6) if ts.size > 1 and ts[-1] > ts[0] else None
            )
            d = devs.get(name)
            cams[name] = CameraSummary(
                frames=len(fs),
                fps=fps,
                shape=list(fs.stored_shape),
                dtype=str(self._h[f"{FRAMES_GROUP}/{name}/images"].dtype),
                pixel_format=fs.pixel_format,
                t_first_us=int(ts[0]) if ts.size else None,
                t_last_us=int(ts[-1]) if ts.size else None,
                dropped_frames=len(d.dropped_frames) if d else None,
                missing_pulses=len(d.missing_pulses) if d else None,
                sync_rms_us=_finite(d.residual_rms_us) if d else None,
                sync_max_us=_finite(d.residual_max_us) if d else None,
            )
        sens: dict[str, EventSensorSummary] = {}
        for name in self.event_sensors:
            es = self.sensor(name)
            g = self._h[f"{EVENTS_GROUP}/{name}"]
            n, span = es.count, es.span
            span_us = span[1] - span[0] if span else 0
            d = devs.get(name)
            sens[name] = EventSensorSummary(
                events=n,
                event_rate_hz=n / (span_us / 1e6) if span_us > 0 else None,
                t_first_us=span[0] if span else None,
                t_last_us=span[1] if span else None,
                span_us=span_us,
                width=int(g.attrs.get(Device.WIDTH, 0)),
                height=int(g.attrs.get(Device.HEIGHT, 0)),
                triggers=es.trigger_count,
                missing_pulses=len(d.missing_pulses) if d else None,
                sync_rms_us=_finite(d.residual_rms_us) if d else None,
                sync_max_us=_finite(d.residual_max_us) if d else None,
            )
        pulses_node = self._f.get(f"{TRIGGER_GROUP}/pulses/index")
        raw_reason = self._f.attrs.get(Root.FAILURE_REASON)
        reason = None if raw_reason is None else attr_text(raw_reason)
        status, recovered = self.status, self.recovered_utc
        verdict = take_verdict(
            status,
            report,
            {k: c.frames for k, c in cams.items()},
            {k: e.events for k, e in sens.items()},
            recovered_utc=recovered,
            failure_reason=reason,
        )
        return TakeSummary(
            path=str(self.path),
            take_id=self.take_id,
            status=status,
            verdict=verdict.verdict,
            verdict_reasons=verdict.reasons,
            schema_version=self.schema_version,
            time_domain=self.time_domain,
            failure_reason=reason,
            recovered_utc=recovered,
            end_reason=self.end_reason,
            cameras=cams,
            event_sensors=sens,
            pulses=int(pulses_node.shape[0]) if isinstance(pulses_node, h5py.Dataset) else 0,
            pulses_seen_by_no_device=list(report.pulses_seen_by_no_device) if report else [],
            losses=list(report.losses) if report else [],
            warnings=list(report.warnings) if report else [],
            parts=self.parts,
        )


def open_take(path: str | Path) -> Take:
    """Open a take read-only; raises TakeError naming the file if it cannot."""
    return Take(path)
