"""What crash recovery reads from a take: the capture pipeline's memory, rebuilt from the file.

The pulse log, every camera's frame times, every event sensor's rising trigger-in edges, the
rig config's trigger rate and sensor settings, and the journal of the last flush -- as if the
repair that was checked (`kept`) had been applied. Nothing here writes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ValidationError

from rigd.core.errors import TakeFormatError
from rigd.core.layout import (
    EVENTS_GROUP,
    FRAMES_GROUP,
    PULSE_SERIES,
    PULSES_PATH,
    SYNC_REPORT_PATH,
    Device,
    Events,
    Frames,
    Pulses,
    Root,
    TriggerEdges,
)
from rigd.core.schema import SyncReport, decode_journal
from rigd.core.settings import EventSensorSettings, WriterConfig
from rigd.sync import DeviceObservations, PulseLog
from rigd.take.evt_read import is_evt_words
from rigd.take.evt_repair import kept_rows
from rigd.take.h5file import attr_text, require_dataset, require_group
from rigd.take.tails import tail_rows


@dataclass(slots=True)
class TakeData:
    """Everything recovery reads from the take, as the capture pipeline had it in memory."""

    status: str
    plan: bool
    failure_reason: str | None
    last_flush_utc: str | None
    flush_count: int | None
    flush_interval_s: float | None
    writer_config: WriterConfig
    rate_hz: float | None
    pulses: PulseLog
    observations: list[DeviceObservations]
    cameras: list[str]
    sensors: list[str]
    frames: dict[str, int]
    events: dict[str, int]
    triggers: dict[str, int]
    n_pulses: int
    last_t: dict[str, int | None]
    slaves: dict[str, str]
    software: set[str]
    journal: dict[str, Any] | None
    stored_report: SyncReport | None
    warnings: list[str] = field(default_factory=list)


def _read_ds(ds: h5py.Dataset, n: int, where: str) -> NDArray[Any]:
    """ds[:n], or a TakeFormatError naming the file and dataset (corrupt chunk, bad filter)."""
    try:
        return np.asarray(ds[:n])
    except (OSError, ValueError) as exc:
        raise TakeFormatError(f"{where}: {ds.name}: cannot be read: {exc}") from exc


def _json_dict(text: str, what: str, warnings: list[str]) -> dict[str, Any]:
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        warnings.append(f"{what} is not valid JSON ({exc}); ignored")
        return {}
    if not isinstance(data, dict):
        warnings.append(f"{what} is not a JSON object; ignored")
        return {}
    return data


def _known_fields(model: type[BaseModel], raw: Any) -> dict[str, Any]:
    """Only the fields this rigd knows: takes from other versions still parse."""
    return {k: v for k, v in raw.items() if k in model.model_fields} if isinstance(raw, dict) else {}


def _writer_config(cfg: dict[str, Any], warnings: list[str]) -> WriterConfig:
    try:
        return WriterConfig.model_validate(_known_fields(WriterConfig, cfg.get("writer")))
    except ValidationError as exc:
        warnings.append(
            f"rig config writer settings unreadable ({exc.error_count()} error(s)); defaults used"
        )
        return WriterConfig()


def _sensor_settings(
    cfg: dict[str, Any], name: str, g: h5py.Group, warnings: list[str]
) -> EventSensorSettings:
    """From the rig config in the take, else the group's own `settings_json`, else defaults."""
    raw: Any = None
    sensors = cfg.get("event_sensors")
    for s in sensors if isinstance(sensors, list) else []:
        if isinstance(s, dict) and s.get("name") == name:
            raw = s.get("settings", {})
    if raw is None and Device.SETTINGS_JSON in g.attrs:
        raw = _json_dict(attr_text(g.attrs[Device.SETTINGS_JSON]), f"{g.name} attr settings_json", warnings)
    if raw is None:
        warnings.append(f"{name}: no settings in the take; trigger-in channel 0 assumed")
    try:
        return EventSensorSettings.model_validate(_known_fields(EventSensorSettings, raw))
    except ValidationError as exc:
        warnings.append(f"{name}: settings unreadable ({exc.error_count()} error(s)); defaults used")
        return EventSensorSettings()


def _rate_hz(cfg: dict[str, Any], pulses: PulseLog, warnings: list[str]) -> float | None:
    trig = cfg.get("trigger")
    settings = trig.get("settings") if isinstance(trig, dict) else None
    rate = settings.get("rate_hz") if isinstance(settings, dict) else None
    if isinstance(rate, int | float) and rate > 0:
        return float(rate)
    if pulses.t_us.size >= 2:
        period = float(np.median(np.diff(pulses.t_us) / np.maximum(np.diff(pulses.index), 1)))
        if period > 0:
            warnings.append(
                f"trigger rate not in the rig config; {1e6 / period:.6g} Hz estimated from the pulses"
            )
            return 1e6 / period
    return None


def _synth_host_times(
    t: NDArray[np.int64], host: NDArray[np.int64], pulses: PulseLog, period_us: float
) -> NDArray[np.int64]:
    """Host times for edges recorded without one (schema 1.0), so the sync engine's coarse
    matching has something to work with: the edge's pulse is counted in whole periods from
    the first edge, taken to be pulse 0 (devices start before the box), and given that
    pulse's host arrival time from a line fitted to the pulse log."""
    steps = np.maximum(np.rint(np.diff(t).astype(np.float64) / period_us), 1.0)
    k = np.concatenate([[0.0], np.cumsum(steps)])
    idx = pulses.index.astype(np.float64)
    h0 = int(pulses.host_time_ns[0])
    rel = (pulses.host_time_ns - h0).astype(np.float64)
    if idx.size >= 2 and np.ptp(idx) > 0:
        slope, icpt = np.polyfit(idx, rel, 1)
    else:
        slope, icpt = period_us * 1e3, float(rel[0]) - float(idx[0]) * period_us * 1e3
    est = np.rint(icpt + slope * k).astype(np.int64) + h0
    return np.where(host < 0, est, host)


@dataclass(slots=True)
class _Devices:
    """What `_read` gathers device by device."""

    observations: list[DeviceObservations] = field(default_factory=list)
    frames: dict[str, int] = field(default_factory=dict)
    events: dict[str, int] = field(default_factory=dict)
    triggers: dict[str, int] = field(default_factory=dict)
    last_t: dict[str, int | None] = field(default_factory=dict)
    slaves: dict[str, str] = field(default_factory=dict)
    software: set[str] = field(default_factory=set)


def read_take(f: h5py.File, path: Path, kept: dict[str, int], *, plan: bool) -> TakeData:
    """Read what the sync engine and the report need, as if `kept` trims were applied."""
    where = str(path)
    warnings: list[str] = []
    cfg = _json_dict(attr_text(require_dataset(f, Root.CONFIG, where)[()]), f"/{Root.CONFIG}", warnings)
    pg = require_group(f, PULSES_PATH, where)
    cols = {k: require_dataset(pg, k, where) for k in PULSE_SERIES}
    n_p = kept.get(pg.name, int(cols[Pulses.INDEX].shape[0]))
    index, t_us, host = (np.asarray(_read_ds(cols[k], n_p, where), np.int64) for k in cols)
    pulses = PulseLog.from_records(index, t_us, host)
    rate = _rate_hz(cfg, pulses, warnings)
    dev = _Devices()
    for name, g in require_group(f, FRAMES_GROUP, where).items():
        _read_camera(dev, name, g, where, kept, warnings)
    period = 1e6 / rate if rate else None
    for name, g in require_group(f, EVENTS_GROUP, where).items():
        _read_event_counts(dev, name, g, where, kept, plan=plan)
        settings = _sensor_settings(cfg, name, g, warnings)
        if settings.sync_mode == "slave" and settings.sync_master is not None:
            dev.slaves[name] = settings.sync_master
        tg = require_group(g, Events.TRIGGER, where)
        dev.triggers[name] = kept.get(
            tg.name, int(require_dataset(tg, TriggerEdges.T_DEVICE, where).shape[0])
        )
        t_r, h_r = _rising_edges(tg, where, dev.triggers[name], settings.trigger_in_channel)
        unknown = int((h_r < 0).sum())
        if unknown and pulses.index.size and period is not None:
            h_r = _synth_host_times(t_r, h_r, pulses, period)
            warnings.append(
                f"{name}: {unknown} trigger edge(s) without a recorded host time (schema 1.0 writer); "
                "matched to pulses assuming its first edge is pulse 0"
            )
        dev.observations.append(DeviceObservations(name, "event_sensor", t_r, h_r))
    journal = _read_journal(f, warnings)
    stored_report = _stored_report(f, warnings) if plan else None
    interval = f.attrs.get(Root.FLUSH_INTERVAL_S)
    count = f.attrs.get(Root.FLUSH_COUNT)
    reason = f.attrs.get(Root.FAILURE_REASON)
    return TakeData(
        status=attr_text(f.attrs.get(Root.STATUS, "")),
        plan=plan,
        failure_reason=None if reason is None else attr_text(reason),
        last_flush_utc=attr_text(f.attrs[Root.LAST_FLUSH_UTC]) if Root.LAST_FLUSH_UTC in f.attrs else None,
        flush_count=None if count is None else int(count),
        flush_interval_s=None if interval is None else float(interval),
        writer_config=_writer_config(cfg, warnings),
        rate_hz=rate,
        pulses=pulses,
        observations=dev.observations,
        cameras=list(dev.frames),
        sensors=list(dev.events),
        frames=dev.frames,
        events=dev.events,
        triggers=dev.triggers,
        n_pulses=n_p,
        last_t=dev.last_t,
        slaves=dev.slaves,
        software=dev.software,
        journal=journal,
        stored_report=stored_report,
        warnings=warnings,
    )


def _read_camera(
    dev: _Devices, name: str, g: h5py.Group, where: str, kept: dict[str, int], warnings: list[str]
) -> None:
    """A camera's frame times as the sync engine sees them, and whether it syncs in software."""
    t_ds = require_dataset(g, Frames.T_EXPOSURE_START_DEVICE, where)
    n = kept.get(g.name, int(t_ds.shape[0]))
    t = np.asarray(_read_ds(t_ds, n, where), np.int64)
    host = np.asarray(_read_ds(require_dataset(g, Frames.HOST_TIME_NS, where), n, where), np.int64)
    counter = np.asarray(_read_ds(require_dataset(g, Frames.FRAME_COUNTER, where), n, where), np.int64)
    dev.observations.append(DeviceObservations(name, "rgb_camera", t, host, counter))
    dev.frames[name], dev.last_t[name] = n, int(t[-1]) if n else None
    info = _json_dict(attr_text(g.attrs.get(Device.INFO_JSON, "{}")), f"{g.name} attr info_json", warnings)
    facts = info.get("facts")
    if isinstance(facts, dict) and facts.get("sync") == "software":
        dev.software.add(name)


def _read_event_counts(
    dev: _Devices, name: str, g: h5py.Group, where: str, kept: dict[str, int], *, plan: bool
) -> None:
    """Events the sealed take will hold (the flushed tail the repair appends included) and the
    device time of the last one."""
    if is_evt_words(g):
        rows = kept_rows(g, kept)
        dev.events[name] = int(rows[:, 2].sum())
        dev.last_t[name] = int(rows[-1, 4]) if rows.shape[0] and not plan else None
        return
    t_ds = require_dataset(g, Events.T, where)
    n_ev = kept.get(g.name, int(t_ds.shape[0]))
    slot, m = (0, 0) if plan else tail_rows(g, n_ev)
    dev.events[name] = n_ev + m
    # During a finalize t is part rig time: the device time of the last event is unknown.
    if m:
        dev.last_t[name] = int(g[f"{Events.TAIL_PREFIX}{Events.T}"][slot, m - 1])
    else:
        dev.last_t[name] = int(t_ds[n_ev - 1]) if n_ev and not plan else None


def _rising_edges(
    tg: h5py.Group, where: str, n_tr: int, channel: int
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Device and host times of the rising trigger-in edges on `channel` (host -1: unknown)."""
    td = np.asarray(_read_ds(require_dataset(tg, TriggerEdges.T_DEVICE, where), n_tr, where), np.int64)
    pol = _read_ds(require_dataset(tg, TriggerEdges.P, where), n_tr, where)
    chan = _read_ds(require_dataset(tg, TriggerEdges.CHANNEL, where), n_tr, where)
    if TriggerEdges.HOST_TIME_NS in tg:
        host = np.asarray(
            _read_ds(require_dataset(tg, TriggerEdges.HOST_TIME_NS, where), n_tr, where), np.int64
        )
    else:
        host = np.full(n_tr, -1, np.int64)
    rising = (pol == 1) & (chan == channel)
    return td[rising], host[rising]


def _stored_report(f: h5py.File, warnings: list[str]) -> SyncReport | None:
    """The sync report a cut-short finalize stored; unparseable, it is kept and not used."""
    node = f.get(SYNC_REPORT_PATH)
    if not isinstance(node, h5py.Dataset):
        return None
    try:
        return SyncReport.model_validate_json(attr_text(node[()]))
    except ValidationError as exc:
        warnings.append(f"/{SYNC_REPORT_PATH} does not parse ({exc.error_count()} error(s)); kept as is")
        return None


def _read_journal(f: h5py.File, warnings: list[str]) -> dict[str, Any] | None:
    """The newest readable journal slot; damage is a warning, never an error (bookkeeping)."""
    node = f.get(Root.JOURNAL)
    if node is None:
        return None
    try:
        found = decode_journal(np.asarray(node[...]))
    except (OSError, ValueError, TypeError) as exc:
        warnings.append(f"/{Root.JOURNAL} unreadable ({exc}); losses recorded before the crash unknown")
        return None
    if found is None:
        warnings.append(f"/{Root.JOURNAL} has no readable slot; losses recorded before the crash unknown")
        return None
    return found[1]
