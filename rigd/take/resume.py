"""Reopening a take whose writer died, so it can be sealed (`rigd.take.seal`).

`resume_take` trims what the kill left half-written (`rigd.take.repair.check_repair`), rebuilds
the per-device stores from the file and hands back a `TakeWriter` over it; a take whose
finalize had started keeps its stored plan (`TakeState.finalize_pending`), so sealing continues
it with the same maps and no time is ever mapped twice.
"""

from __future__ import annotations

import logging
from pathlib import Path

import h5py

from rigd.core.errors import TakeError, TakeFormatError, TakeTruncatedError
from rigd.core.layout import EVENTS_GROUP, FRAMES_GROUP, PULSES_PATH, TRIGGER_GROUP, Device, Root
from rigd.core.settings import WriterConfig
from rigd.take.event_store import event_store
from rigd.take.finalize import FinalizePlan
from rigd.take.h5file import (
    TRUNCATED_EOF_ATTR,
    attr_text,
    check_header,
    open_extended,
    open_h5,
    require_group,
)
from rigd.take.repair import Trim, check_repair
from rigd.take.sinks import CameraSink, PulseSink
from rigd.take.take_state import WRITE_CHUNK_CACHE_BYTES, TakeState
from rigd.take.writer import TakeWriter

__all__ = ["resume_take"]

log = logging.getLogger(__name__)


def resume_take(path: str | Path, config: WriterConfig, *, extend_truncated: bool = False) -> TakeWriter:
    """Reopen a take whose writer died, so it can be finalized (or a cut-short finalize
    continued, `rigd.take.seal.continue_finalize`).

    `check_repair` first trims what the kill left half-written (`state.repairs`). A take whose
    finalize had started is never trimmed (all its data was flushed before finalize began),
    only checked. `config` gives the codecs of the datasets finalize adds. A take truncated
    by a failed write raises TakeTruncatedError unless `extend_truncated`: then the file is
    extended with a hole to the length HDF5 expects (no recorded byte changes) and whatever
    lay past the old end is trimmed as never written. Raises TakeInUseError if a live
    process holds the file, TakeFormatError (naming the file and dataset) if it is not a
    readable take.
    """
    path = Path(path)
    try:
        f = open_h5(path, "r+", rdcc_nbytes=WRITE_CHUNK_CACHE_BYTES)
    except TakeTruncatedError as exc:
        if not extend_truncated:
            raise
        f = open_extended(path, exc)
    try:
        return TakeWriter.over(_resume_open(path, f, config))
    except BaseException:
        f.close()
        raise


def _resume_open(path: Path, f: h5py.File, config: WriterConfig) -> TakeState:
    version = check_header(f, path)
    status = attr_text(f.attrs.get(Root.STATUS, ""))
    if status == "complete":
        raise TakeError(f"{path}: take is already complete; nothing to resume")
    plan_text = f.attrs.get(Root.FINALIZE_PLAN)
    plan = None if plan_text is None else FinalizePlan.from_json(attr_text(plan_text), str(path))
    repairs = _resume_repairs(f, path, plan)
    where = str(path)
    pulses = PulseSink.reopen(require_group(f, PULSES_PATH, where), where)
    state = TakeState(path, f, config, pulses, status="finalizing" if plan is not None else "recording")
    state.version = version
    state.repairs = repairs
    state.plan = plan
    state.flush_count = int(f.attrs.get(Root.FLUSH_COUNT, 0))
    _rebuild_stores(state)
    if plan is None:
        f.flush()  # the tails check_repair merged are redundant once this is on disk
        state.drop_tails()
    else:
        missing = [n for n in (*state.cameras, *state.stores) if n not in plan.maps]
        if missing:
            raise TakeFormatError(f"{path}: /: attr {Root.FINALIZE_PLAN} has no clock map for {missing}")
    f.flush()
    log.info(
        "take %s resumed (%s; %d trim(s)%s)",
        path,
        status,
        len(repairs),
        ", finalize to continue" if plan is not None else "",
    )
    return state


def _rebuild_stores(state: TakeState) -> None:
    """Writer state from what is in the file (after check_repair every group is consistent)."""
    f = state.f
    where = str(state.path)
    state.has_trigger = Device.INFO_JSON in f[TRIGGER_GROUP].attrs
    for name, g in require_group(f, EVENTS_GROUP, where).items():
        state.stores[name] = event_store(name, g, where, state.config)
    for name, g in require_group(f, FRAMES_GROUP, where).items():
        state.cameras[name] = CameraSink.reopen(name, g, where)


def _resume_repairs(f: h5py.File, path: Path, plan: FinalizePlan | None) -> list[Trim]:
    """Trim what the kill left half-written; a take whose finalize had started is only
    checked (its `t` is part rig, part device time now, so only lengths can be)."""
    if plan is None:
        repairs = check_repair(f, path, apply=True)
        if TRUNCATED_EOF_ATTR in f.attrs:  # nothing past the old end is referenced any more
            del f.attrs[TRUNCATED_EOF_ATTR]
        return repairs
    found = check_repair(f, path, apply=False, check_order=False)
    if found:
        what = "; ".join(f"{t.hpath}: {t.reason}" for t in found)
        raise TakeFormatError(
            f"{path}: finalize had started, yet the data is inconsistent ({what}); refusing to touch it"
        )
    return []
