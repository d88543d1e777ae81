"""Joining a multi-host take: the hosts' part files become one take file (docs/take-format.md,
"Multi-host takes"; decision 0033).

Each host of a multi-host rig captures its own devices into a normal, complete take, its part
`<stem>.<host>.part.h5`, fitted to the coordinator's trigger pulses. Once the parts are in one
directory, `join_take` writes `<stem>.h5` beside them: the coordinator's root attributes, its
`/trigger`, a merged `/sync` (rigd/take/parts_merge.py), a copy of the parts' calibrations, and
`/events/<sensor>` and `/frames/<camera>` as HDF5 external links, by relative name, into the
part that holds each device. A root attribute `parts_json` lists every part (host, file,
devices, sha256, size, status, verdict), so the take says which files it needs and what state
they were in. A host whose part is missing, unsealed or not this take's costs its devices only:
they are not linked, each gets a loss record and the verdict is `degraded`. Joining again (after
`rigd recover` on that host and `rigd takes gather`) rewrites the file.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from rigd.core.devices import DeviceInfo
from rigd.core.errors import TakeError, TakeFormatError, TakeInUseError
from rigd.core.layout import (
    CALIBRATION_GROUP,
    EVENTS_GROUP,
    FRAMES_GROUP,
    PULSES_PATH,
    SYNC_GROUP,
    TRIGGER_GROUP,
    Pulses,
    Root,
    Sync,
)
from rigd.core.schema import SyncReport
from rigd.take.h5file import fsync_dir, open_checked
from rigd.take.manifest import PART_NAME, PartEntry, PartStatus, dump_manifest, read_manifest
from rigd.take.parts_merge import (
    PartRecords,
    device_kinds,
    lost_devices,
    merge_config,
    merge_reports,
    merge_window_outside,
)
from rigd.take.parts_truth import device_info, rebase_ground_truth
from rigd.take.reader import Take
from rigd.take.verdict import TakeVerdict

log = logging.getLogger(__name__)

_HASH_BLOCK = 4 << 20
#: Root attributes of the coordinator's part the joined take does not take over.
_NOT_COPIED = frozenset({Root.TAKE_ID, Root.WINDOW_OUTSIDE, Root.PARTS})


@dataclass(frozen=True, slots=True)
class PartRef:
    """One host's part: its file in the joined take's directory (None: not there) and the
    devices the rig's plan gives that host."""

    host: str
    file: Path | None
    devices: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class JoinResult:
    """The joined take, its parts as the manifest records them, and its verdict."""

    path: Path
    parts: list[PartEntry]
    verdict: TakeVerdict

    @property
    def missing_devices(self) -> list[str]:
        """Devices of the parts that are not linked (their data is not in the take)."""
        return [d for p in self.parts if not p.linked for d in p.devices]


def part_name(stem: str, host: str) -> str:
    """`<stem>.<host>.part.h5`: the file a host writes its devices of take `<stem>` into."""
    return f"{stem}.{host}.part.h5"


def file_sha256(path: Path) -> str:
    """The file's sha256, read in blocks (a part can be gigabytes)."""
    h = hashlib.sha256()
    with path.open("rb") as f:
        while block := f.read(_HASH_BLOCK):
            h.update(block)
    return h.hexdigest()


@dataclass(slots=True)
class _Part:
    ref: PartRef
    entry: PartEntry
    records: PartRecords | None = None
    path: Path | None = None


def join_take(
    out: Path, coordinator: Path, parts: Sequence[PartRef], *, missing: Mapping[str, str] | None = None
) -> JoinResult:
    """Write the joined take `out` from `parts` (one per host, the coordinator's among them);
    `coordinator`: the part file that owns the trigger; `missing`: why a host's part is not
    there, by host. Raises TakeError when the parts cannot form one take (a device in two
    parts, a part holding a device its host does not run, the coordinator's part unsealed)."""
    out = Path(out)
    directory = out.parent.resolve()
    _check_refs(out, parts)
    coord_ref = next((r for r in parts if r.file is not None and _same(directory, r.file, coordinator)), None)
    if coord_ref is None:
        raise TakeError(f"{out}: the coordinator's part {coordinator} is not one of the parts joined")
    why = dict(missing or {})
    previous = _previous_calibration(out)
    coord = _read_part(out, coord_ref, None, why, coordinator=True)
    if coord.records is None or coord.path is None:
        raise TakeError(
            f"{out}: the coordinator's part {coordinator} is {coord.entry.status}: {coord.entry.reason}; "
            "a take is joined around it (`rigd recover` seals it)"
        )
    pulses = _pulses(coord.path)
    others = [_read_part(out, r, pulses, why) for r in parts if r is not coord_ref]
    linked = [p for p in others if p.records is not None]
    records = [p.records for p in linked if p.records is not None]
    config = merge_config(coord.records, records)
    kinds = device_kinds(config)
    lost = []
    for p in [coord, *others]:
        if not p.entry.linked:
            lost += lost_devices(p.ref.devices, f"host {p.ref.host}: {p.entry.reason}", kinds)
        else:
            lost += lost_devices(
                _absent(p), f"host {p.ref.host}'s part {p.entry.file} holds no group for it", kinds
            )
    report = merge_reports(coord.records, records, lost)
    entries = [coord.entry, *(p.entry for p in others)]
    tmp = out.with_name(f".{out.name}.joining")
    try:
        with h5py.File(tmp, "w") as f:
            _write(f, out, coord, linked, entries, config, report, previous)
            _write_window(f, coord.records, records)
            f.flush()
            os.fsync(f.id.get_vfd_handle())
        os.replace(tmp, out)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(out.parent)
    with Take(out) as take:
        summary = take.summary()
    verdict = TakeVerdict(verdict=summary.verdict, reasons=summary.verdict_reasons)
    log.info("joined %s from %d part(s): %s", out, sum(e.linked for e in entries), verdict.line())
    return JoinResult(out, entries, verdict)


def _same(directory: Path, file: Path, other: Path) -> bool:
    return (directory / file).resolve() == (directory / other).resolve()


def _check_refs(out: Path, parts: Sequence[PartRef]) -> None:
    if out.suffix != ".h5":
        raise TakeError(f"{out}: a joined take is named <stem>.h5")
    hosts = [r.host for r in parts]
    if len(set(hosts)) != len(hosts):
        raise TakeError(f"{out}: a host has two parts ({', '.join(hosts)})")
    owner: dict[str, str] = {}
    for r in parts:
        for d in r.devices:
            if d in owner:
                raise TakeError(f"{out}: device {d} is planned on hosts {owner[d]} and {r.host}")
            owner[d] = r.host
        if r.file is None:
            continue
        if not re.fullmatch(PART_NAME, r.file.name):
            raise TakeError(f"{out}: host {r.host}: part {r.file.name!r} is not named <stem>.<host>.part.h5")
        if (out.parent / r.file).resolve().parent != out.parent.resolve():
            raise TakeError(
                f"{out}: host {r.host}: part {r.file} is not in the take's directory {out.parent}"
            )


def _entry(ref: PartRef, status: PartStatus, reason: str | None, coordinator: bool, **kw: Any) -> PartEntry:
    name = None if ref.file is None else ref.file.name
    return PartEntry(
        host=ref.host,
        file=name,
        devices=list(ref.devices),
        coordinator=coordinator,
        status=status,
        reason=reason,
        **kw,
    )


def _read_part(
    out: Path,
    ref: PartRef,
    pulses: tuple[np.ndarray, np.ndarray] | None,
    why: Mapping[str, str],
    *,
    coordinator: bool = False,
) -> _Part:
    """The part as the manifest will record it, and its records when it can be linked."""
    fix = f"`rigd recover` on host {ref.host}, then `rigd takes gather {out.name}`"
    path = None if ref.file is None else out.parent / ref.file.name
    if path is None or not path.exists():
        reason = why.get(ref.host) or (
            f"no part file {ref.file.name} in {out.parent}" if ref.file else "no part file"
        )
        return _Part(ref, _entry(ref, "missing", f"{reason} ({fix})", coordinator))
    size, sha = path.stat().st_size, file_sha256(path)
    stat: dict[str, Any] = {"size": size, "sha256": sha}
    try:
        open_checked(path, "r", part=True).close()  # a part holds no link and is not joined
        with Take(path) as take:
            status, summary = take.status, take.summary()
            if status != "complete":
                st: PartStatus = "unfinished" if status == "recording" else "failed"
                reason = f"part {path.name} is {summary.verdict} (status {status}) ({fix})"
                return _Part(ref, _entry(ref, st, reason, coordinator, verdict=summary.verdict, **stat))
            held = [*take.cameras, *take.event_sensors]
            extra = sorted(set(held) - set(ref.devices))
            if extra:
                raise TakeError(
                    f"{out}: host {ref.host}'s part {path.name} holds {', '.join(extra)}, which the plan "
                    f"does not give that host (its devices: {', '.join(ref.devices) or 'none'})"
                )
            report = take.sync_report
            if report is None:
                raise TakeFormatError(f"{path}: complete but holds no sync report")
            window = take.window_outside or {}
            records = PartRecords(ref.host, ref.devices, report, take.config, window)
    except TakeInUseError:
        reason = f"part {path.name} is still being written (its HDF5 lock is held) ({fix})"
        return _Part(ref, _entry(ref, "unfinished", reason, coordinator, **stat))
    except TakeFormatError as exc:
        return _Part(ref, _entry(ref, "damaged", f"part {path.name} is damaged: {exc}", coordinator, **stat))
    if pulses is not None and not _pulses_follow(path, pulses):
        reason = (
            f"part {path.name} holds other trigger pulses than the coordinator's: not a part of this take"
        )
        return _Part(ref, _entry(ref, "foreign", reason, coordinator, verdict=summary.verdict, **stat))
    entry = _entry(ref, "complete", None, coordinator, verdict=summary.verdict, **stat)
    return _Part(ref, entry, records, path)


def _pulses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    with Take(path) as take:
        p = take.pulses()
    return p.index, p.t_us


def _pulses_follow(path: Path, coordinator: tuple[np.ndarray, np.ndarray]) -> bool:
    """Whether the part's pulses are the coordinator's (a host that died holds a prefix)."""
    index, t_us = _pulses(path)
    n = index.size
    return n <= coordinator[0].size and bool(
        np.array_equal(index, coordinator[0][:n]) and np.array_equal(t_us, coordinator[1][:n])
    )


def _absent(p: _Part) -> list[str]:
    """Planned devices a linked part holds no group for."""
    assert p.path is not None
    with open_checked(p.path, "r", part=True) as f:
        held = {*f.get(EVENTS_GROUP, {}).keys(), *f.get(FRAMES_GROUP, {}).keys()}
    return [d for d in p.ref.devices if d not in held]


def _previous_calibration(out: Path) -> Path | None:
    """A joined take being rewritten whose `/calibration` is to be kept: what `rigd calibrate
    --into-take` wrote into it wins over the parts' copies. A file there that is no joined
    take is never overwritten."""
    if not out.exists():
        return None
    try:
        with open_checked(out, "r") as f:
            if read_manifest(f, out) is None:
                raise TakeError(f"{out}: exists and is not a joined take; not overwritten")
            return out if isinstance(f.get(CALIBRATION_GROUP), h5py.Group) else None
    except TakeFormatError as exc:
        log.warning(
            "%s: the joined take being rewritten cannot be read (%s); its calibrations are not kept", out, exc
        )
        return None


def _copy_calibration(src: h5py.File, calib: h5py.Group, names: Any, *, attrs: bool) -> None:
    """`src`'s /calibration groups of the devices in `names` (all: None) into `calib`, where
    not there yet; its attributes (the board pose) too with `attrs`."""
    root = src.get(CALIBRATION_GROUP)
    if not isinstance(root, h5py.Group):
        return
    if attrs:
        calib.attrs.update(dict(root.attrs))
    for name in root:
        if (names is None or name in names) and name not in calib:
            src.copy(root[name], calib, name)


def _write(
    f: h5py.File,
    out: Path,
    coord: _Part,
    linked: Sequence[_Part],
    entries: Sequence[PartEntry],
    config: dict[str, Any],
    report: SyncReport,
    previous: Path | None,
) -> None:
    assert coord.path is not None
    with open_checked(coord.path, "r", part=True) as src:
        for key, value in src.attrs.items():
            if key not in _NOT_COPIED:
                f.attrs[key] = value
        src.copy(src[TRIGGER_GROUP], f, TRIGGER_GROUP)
        if PULSES_PATH not in f or Pulses.T_US not in f[PULSES_PATH]:
            raise TakeFormatError(f"{coord.path}: /{PULSES_PATH} is missing")
    f.attrs[Root.TAKE_ID] = out.stem
    f.attrs[Root.PARTS] = dump_manifest(list(entries))
    f.create_dataset(Root.CONFIG, data=json.dumps(config), dtype=h5py.string_dtype("utf-8"))
    events, frames = f.create_group(EVENTS_GROUP), f.create_group(FRAMES_GROUP)
    sync = f.create_group(SYNC_GROUP)
    sync.create_dataset(Sync.REPORT, data=report.model_dump_json(), dtype=h5py.string_dtype("utf-8"))
    devs = sync.create_group(Sync.DEVICES)
    calib = f.create_group(CALIBRATION_GROUP)
    infos: dict[str, DeviceInfo | None] = {}
    if previous is not None:
        with open_checked(previous, "r") as src:
            _copy_calibration(src, calib, None, attrs=True)
    for p in [coord, *linked]:
        assert p.path is not None
        with open_checked(p.path, "r", part=True) as src:
            for group, dest in ((EVENTS_GROUP, events), (FRAMES_GROUP, frames)):
                for name in src.get(group, {}):
                    dest[name] = h5py.ExternalLink(p.path.name, f"/{group}/{name}")
                    infos[name] = device_info(src[f"{group}/{name}"])
            src_devs = src.get(f"{SYNC_GROUP}/{Sync.DEVICES}", {})
            for name in src_devs:
                if (name in p.ref.devices or p is coord) and name not in devs:
                    src.copy(src_devs[name], devs, name)
            keep = p is coord and previous is None
            _copy_calibration(src, calib, None if p is coord else p.ref.devices, attrs=keep)
    order = [d.get("name") for key in ("cameras", "event_sensors") for d in config.get(key, [])]
    rebase_ground_truth(f, {n: infos[n] for n in [*order, *infos] if n in infos})
    if not len(calib) and not len(calib.attrs):
        del f[CALIBRATION_GROUP]


def _write_window(f: h5py.File, coord: PartRecords, others: Sequence[PartRecords]) -> None:
    if coord.window_outside or any(p.window_outside for p in others):
        f.attrs[Root.WINDOW_OUTSIDE] = json.dumps(merge_window_outside(coord, others), sort_keys=True)
