"""What a joined multi-host take says about the whole rig, merged from its parts' own records.

Every part is a sealed take of its host's devices, fitted to the same trigger pulses, so each
device's clock map and report row come from its own part unchanged; what is about the trigger
(pulse counts, the box's log, the host-box link) comes from the coordinator, which owns the
box (a follower's own trigger-link counters are kept as `<name>@<host>`). Losses and warnings
are the union of the parts' (a record two parts both carry, such as a
pulse the box failed to log, counts once). A host whose part is not there, not sealed or not
this take's costs its devices: one loss record each, which the verdict names.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

from rigd.core.schema import LossKind, LossRecord, SyncReport


@dataclass(slots=True)
class PartRecords:
    """What the join takes from one readable part: its host, devices and records."""

    host: str
    devices: tuple[str, ...]
    report: SyncReport
    config: dict[str, Any]
    window_outside: dict[str, Any] = field(default_factory=dict)


T = TypeVar("T")


def _unique(items: Sequence[T]) -> list[T]:
    out: list[T] = []
    for item in items:
        if item not in out:
            out.append(item)
    return out


def merge_reports(
    coordinator: PartRecords, others: Sequence[PartRecords], lost: Sequence[LossRecord]
) -> SyncReport:
    """The joined take's sync report (see the module docstring); `lost`: one record per device
    of a part that is not linked."""
    parts = [coordinator, *others]
    report = coordinator.report.model_copy(deep=True)
    report.devices = {name: dev for p in parts for name, dev in p.report.devices.items() if name in p.devices}
    seen_by_none = set(coordinator.report.pulses_seen_by_no_device)
    for p in others:
        seen_by_none &= set(p.report.pulses_seen_by_no_device)
    report.pulses_seen_by_no_device = sorted(seen_by_none)
    report.losses = _unique([*(rec for p in parts for rec in p.report.losses), *lost])
    counters: dict[str, dict[str, int]] = {}
    for p in parts:
        for key, values in p.report.device_counters.items():
            # a follower's own non-device counters (its remote trigger) are kept under its host
            name = key if (p is coordinator or key in p.devices) else f"{key}@{p.host}"
            counters.setdefault(name, values)
    report.device_counters = counters
    for p in others:  # a follower's own trigger link (its remote trigger), kept under its host
        for key, value in p.report.trigger_link.items():
            report.trigger_link.setdefault(f"{key}@{p.host}", value)
    report.warnings = _unique([w for p in parts for w in p.report.warnings])
    return report


def merge_config(coordinator: PartRecords, others: Sequence[PartRecords]) -> dict[str, Any]:
    """The coordinator's rig config with any camera or event sensor only another part's config
    names added (a host's session may carry only its own devices)."""
    config = json.loads(json.dumps(coordinator.config))
    for key in ("cameras", "event_sensors"):
        have = config.setdefault(key, [])
        names = {d.get("name") for d in have if isinstance(d, dict)}
        for p in others:
            for dev in p.config.get(key, []):
                if isinstance(dev, dict) and dev.get("name") in p.devices and dev.get("name") not in names:
                    have.append(dev)
                    names.add(dev.get("name"))
    return config


def merge_window_outside(coordinator: PartRecords, others: Sequence[PartRecords]) -> dict[str, Any]:
    """`window_outside_json`: the coordinator's (its devices and the trigger), each other
    part's entries for its own devices."""
    merged = dict(coordinator.window_outside)
    for p in others:
        merged.update({k: v for k, v in p.window_outside.items() if k in p.devices})
    return merged


def device_kinds(config: Mapping[str, Any]) -> dict[str, LossKind]:
    """What each device of a rig config records: a camera frames, an event sensor events."""
    kinds: dict[str, LossKind] = {}
    for key, kind in (("cameras", "frames"), ("event_sensors", "events")):
        for dev in config.get(key, []):
            if isinstance(dev, dict) and isinstance(dev.get("name"), str):
                kinds[dev["name"]] = kind  # type: ignore[assignment]
    return kinds


def lost_devices(devices: Sequence[str], why: str, kinds: Mapping[str, LossKind]) -> list[LossRecord]:
    """One loss record (count unknown) per device whose data the joined take does not hold."""
    out = []
    for name in devices:
        kind = kinds.get(name)
        reason = why if kind is not None else f"{why} (device kind unknown: not in the rig config)"
        out.append(LossRecord(device=name, what=kind or "events", count=0, reason=reason))
    return out
