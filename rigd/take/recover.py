"""Seal takes whose writer died (SIGKILL, power to the process, OOM): find, repair, finalize.

A take is unfinished when its status is still "recording" (the process died while capturing,
or between the last flush and finalize) or when a finalize started and never completed.
`recover_take` rebuilds what the capture pipeline had in memory from the file itself -- the
pulse log, every camera's frame times, every event sensor's rising trigger-in edges, and the
loss bookkeeping of the last flush (`/journal_json`; `recover_read`) -- and seals it through
`rigd.take.seal`, the same fit, report and finalize the capture pipeline ends a take with.
What the kill left half-written is trimmed (`check_repair`) and reported, never dropped
silently; recorded data is never deleted otherwise. A take a live process holds (HDF5 file
lock) is left untouched.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from functools import partial
from pathlib import Path
from typing import Literal

import h5py
import hdf5plugin  # noqa: F401  (registers the LZ4 / Zstd filters with h5py)
from pydantic import BaseModel, ConfigDict, Field

from rigd.core.errors import (
    NotATakeError,
    SyncError,
    TakeError,
    TakeFormatError,
    TakeInUseError,
    TakeTruncatedError,
)
from rigd.core.layout import Root, Status, TimeDomain
from rigd.core.schema import SCHEMA_NAME, LossKind, LossRecord
from rigd.core.settings import WriterConfig
from rigd.sync import SyncResult
from rigd.take.h5file import (
    ZeroPadded,
    attr_text,
    check_header,
    checked,
    open_h5,
    utc_now,
)
from rigd.take.recover_read import TakeData, read_take
from rigd.take.repair import Trim, check_repair
from rigd.take.resume import resume_take
from rigd.take.seal import Bookkeeping, Seal, TakeEnd, fit_take, journal_losses, mark_recovered, seal_take
from rigd.take.writer import TakeWriter

log = logging.getLogger(__name__)

Outcome = Literal[
    "sealed",  # finalized: status complete, times in rig time
    "sealed_failed",  # sealed with status failed and a reason (no rig time could be fitted)
    "in_use",  # a live process holds the file; untouched
    "not_needed",  # already complete, or failed by its own writer
    "would_seal",  # dry run of "sealed"
    "would_seal_failed",  # dry run of "sealed_failed"
]
_SEALED: frozenset[str] = frozenset(
    {"sealed", "sealed_failed", "not_needed", "would_seal", "would_seal_failed"}
)


class RecoveryReport(BaseModel):
    """What recovery found and did to one take; stored in the take as `recovery_report_json`."""

    model_config = ConfigDict(extra="forbid")

    path: str
    outcome: Outcome
    sealed: bool = Field(description="The take is (or, in a dry run, would be) in a final state.")
    dry_run: bool = False
    status_before: str | None = None
    status_after: str | None = None
    finalize_resumed: bool = Field(False, description="A finalize cut short by the crash was continued.")
    reason: str | None = Field(None, description="Why the take is not sealed, or sealed as failed.")
    failure_reason_before: str | None = None
    trims: list[Trim] = Field(default_factory=list)
    frames: dict[str, int] = Field(default_factory=dict, description="Frames kept, by camera.")
    events: dict[str, int] = Field(default_factory=dict, description="Events kept, by sensor.")
    triggers: dict[str, int] = Field(default_factory=dict, description="Trigger-in edges kept, by sensor.")
    pulses: int = 0
    losses_added: list[LossRecord] = Field(
        default_factory=list, description="Loss records recovery added (trims, the crash itself)."
    )
    journal_losses: int = Field(0, description="Loss records merged from the last flush's journal.")
    truncated_bytes: int = Field(
        0, description="Bytes a failed write (disk full) left missing at the end; extended with a hole."
    )
    warnings: list[str] = Field(default_factory=list)
    last_flush_utc: str | None = None
    flush_count: int | None = None
    flush_interval_s: float | None = None

    def line(self) -> str:
        """One line for people: what happened, what was kept, what was cut."""
        kept = f"{sum(self.frames.values())} frames, {sum(self.events.values())} events, {self.pulses} pulses"
        cut = f"; trimmed {len(self.trims)} group(s)" if self.trims else ""
        lost = sum(r.count for r in self.losses_added)
        unknown = sum(1 for r in self.losses_added if r.count == 0)
        head = {
            "sealed": "sealed complete" + (" (finalize resumed)" if self.finalize_resumed else ""),
            "sealed_failed": "sealed FAILED",
            "in_use": "in use by a live writer; left untouched",
            "not_needed": f"{self.status_before}; nothing to recover",
            "would_seal": "would seal complete" + (" (finalize resumed)" if self.finalize_resumed else ""),
            "would_seal_failed": "would seal FAILED",
        }[self.outcome]
        if self.outcome in ("in_use", "not_needed"):
            return f"{self.path}: {head}"
        why = f": {self.reason}" if self.reason else ""
        more = f" and {unknown} loss(es) of unknown count" if unknown else ""
        return f"{self.path}: {head}{why} ({kept}{cut}; {lost} item(s){more} recorded as lost)"


def _failed_unsealed(f: h5py.File) -> bool:
    """Marked failed by its own writer (disk full, a fault) and never finalized nor recovered:
    its times are still in device clock, and recovery can seal what was flushed."""
    return (
        attr_text(f.attrs.get(Root.STATUS, "")) == Status.FAILED
        and attr_text(f.attrs.get(Root.TIME_DOMAIN, TimeDomain.DEVICE)) == TimeDomain.DEVICE
        and Root.RECOVERED_UTC not in f.attrs
        and Root.FINALIZE_STARTED_UTC not in f.attrs
        and Root.FINALIZE_PLAN not in f.attrs
    )


def _needs_recovery(f: h5py.File, truncated: bool) -> bool:
    """Still recording, failed by its writer before finalize, a finalize that started and did
    not finish (and was not sealed), or a file a failed write left too short for HDF5 to open."""
    status = attr_text(f.attrs.get(Root.STATUS, ""))
    if truncated and status != Status.COMPLETE:
        return True
    if status == Status.COMPLETE:
        return False
    if status == Status.RECORDING or Root.FINALIZE_PLAN in f.attrs or _failed_unsealed(f):
        return True
    return Root.FINALIZE_STARTED_UTC in f.attrs and Root.RECOVERED_UTC not in f.attrs


def needs_recovery(path: str | Path) -> bool:
    """Whether `recover_take` has something to do for this one take (the predicate
    `recover_dir.scan_dir` applies to each file). A take a live process holds counts as
    unfinished (its state cannot be read). Raises TakeError / TakeFormatError, naming the
    file, for a file that is not a readable rigd take."""
    p = Path(path)
    try:
        f, truncated = open_view(p)
    except TakeInUseError:
        return True
    with f:
        schema = attr_text(f.attrs.get(Root.SCHEMA, ""))
        if schema != SCHEMA_NAME:
            raise NotATakeError(f"{p}: /: attr schema is {schema!r}, not a rigd take")
        return _needs_recovery(f, truncated is not None)


def open_view(path: Path) -> tuple[h5py.File, TakeTruncatedError | None]:
    """Open read-only; a take truncated by a failed write through a zero-padded view."""
    try:
        return open_h5(path, "r"), None
    except TakeTruncatedError as exc:
        try:
            return checked(path, h5py.File(ZeroPadded(path, exc.stored_eof), "r"), exc.stored_eof), exc
        except OSError as exc2:
            raise TakeFormatError(f"{path}: truncated and unreadable even padded: {exc2}") from exc2


def recover_take(path: str | Path, *, dry_run: bool = False) -> RecoveryReport:
    """Repair and seal one unfinished take; see the module docstring and docs/take-format.md.

    Returns the report (also stored in the take as `recovery_report_json`). A take a live
    process holds comes back "in_use", untouched. Raises TakeError / TakeFormatError, naming
    the file and the dataset, for a file that is not a readable rigd take.
    """
    path = Path(path)
    try:
        return _recover(path, dry_run=dry_run)
    except TakeInUseError as exc:
        log.warning("%s", exc)
        return RecoveryReport(
            path=str(path), outcome="in_use", sealed=False, dry_run=dry_run, reason=str(exc)
        )


@contextmanager
def _reading(path: Path, what: str) -> Iterator[None]:
    """HDF5's own errors from a damaged file (a structure past the end, a broken heap) as one
    line naming the file and the step, instead of a bare OSError or KeyError."""
    try:
        yield
    except TakeFormatError as exc:
        raise TakeFormatError(f"{exc}; {_NOTHING_SAVED}") from exc
    except (OSError, KeyError, ValueError) as exc:
        raise TakeFormatError(
            f"{path}: damaged beyond what recovery repairs ({what}): {type(exc).__name__}: {exc}; "
            f"{_NOTHING_SAVED}"
        ) from exc


#: What a take recovery cannot read comes to: it stops before writing anything.
_NOTHING_SAVED = "recovery saved nothing of this take and left the file as it was"


def _recover(path: Path, *, dry_run: bool) -> RecoveryReport:
    f, truncated = open_view(path)
    with f:
        with _reading(path, "reading the header"):
            check_header(f, path)
        status = attr_text(f.attrs.get(Root.STATUS, ""))
        rr = RecoveryReport(
            path=str(path), outcome="not_needed", sealed=True, dry_run=dry_run, status_before=status
        )
        if not _needs_recovery(f, truncated is not None):
            log.info("take %s is %s; nothing to recover", path, status)
            return rr
        plan = Root.FINALIZE_PLAN in f.attrs
        if truncated is not None:
            rr.truncated_bytes = truncated.stored_eof - truncated.eof
            rr.warnings.append(
                f"the file ends {rr.truncated_bytes} bytes short of what its header records (a write "
                "failed: disk full?); it is extended with a hole and nothing past the old end is used"
            )
        if status == "failed" and not plan and not _failed_unsealed(f):
            # Already sealed failed (or part rig time), only truncated since: repair, keep it.
            with _reading(path, "checking the datasets"):
                trims = check_repair(f, path, apply=False, data_end=truncated.eof if truncated else None)
            return _repair_only(path, rr, trims, dry_run=dry_run)
        if not plan and Root.FINALIZE_STARTED_UTC in f.attrs:
            reason = (
                "finalize was interrupted in a take without a finalize plan (written by rigd before "
                "schema 1.1): event times are part rig, part device time and cannot be told apart"
            )
            return _seal_unresumable(path, rr, reason, dry_run=dry_run)
        # A finalize in progress has rewritten part of t: its order says nothing about damage.
        with _reading(path, "checking the datasets"):
            trims = check_repair(
                f, path, apply=False, check_order=not plan, data_end=truncated.eof if truncated else None
            )
        if plan and trims:  # finalize starts only on consistent data: this is not a crash's doing
            what = "; ".join(f"{t.hpath}: {t.reason}" for t in trims)
            raise TakeFormatError(f"{path}: finalize had started, yet the data is inconsistent ({what})")
        with _reading(path, "reading the recorded data"):
            data = read_take(f, path, {t.hpath: t.after for t in trims}, plan=plan)
    rr.trims = trims
    rr.failure_reason_before = data.failure_reason
    rr.frames, rr.events, rr.triggers, rr.pulses = data.frames, data.events, data.triggers, data.n_pulses
    rr.last_flush_utc, rr.flush_count, rr.flush_interval_s = (
        data.last_flush_utc,
        data.flush_count,
        data.flush_interval_s,
    )
    rr.warnings.extend(data.warnings)
    if data.plan:
        return _continue_finalize(path, rr, data, dry_run=dry_run)
    return _finalize_crashed(path, rr, data, trims, dry_run=dry_run)


# -- sync and bookkeeping ------------------------------------------------------------------
def _crash_note(data: TakeData) -> str:
    when = (
        f"the last flush (#{data.flush_count}, {data.last_flush_utc})"
        if data.last_flush_utc
        else "the last flush"
    )
    span = f"at most {data.flush_interval_s:g} s" if data.flush_interval_s else "one flush interval"
    if data.status == "failed":
        return (
            f"the take was marked failed by its writer ({data.failure_reason}): data after {when} "
            f"may never have been written ({span})"
        )
    return f"the take ended by a crash of its writer: data after {when} was never written ({span})"


def _crash_losses(data: TakeData) -> list[LossRecord]:
    """One record per device: something after the last flush was lost, how much is unknown."""
    note = _crash_note(data)
    kinds: list[tuple[str, LossKind]] = [
        *((n, "frames") for n in data.cameras),
        *((n, "events") for n in data.sensors),
        ("trigger", "pulses"),
    ]
    out = []
    for name, what in kinds:
        t = data.last_t.get(name)
        after = f"; last stored at device t={t} us" if t is not None else ""
        out.append(LossRecord(device=name, what=what, count=0, reason=f"{note}; count unknown{after}"))
    return out


def _fit(data: TakeData, losses: list[LossRecord]) -> tuple[TakeEnd | None, SyncResult | None, str | None]:
    """The fit `seal_take` finalizes with, from what the file holds; a reason instead when it
    cannot tie any device clock to rig time."""
    if data.flush_count == 0:
        return None, None, "the writer died before its first flush: the take holds no recorded data"
    if data.pulses.index.size == 0:
        return (
            None,
            None,
            "no trigger pulse was flushed before the crash: no device clock can be tied to rig time",
        )
    if data.rate_hz is None:
        return None, None, "the trigger rate is unknown (no rig config in the take and too few pulses)"
    end = TakeEnd(
        data.pulses,
        data.observations,
        data.rate_hz,
        losses,
        data.cameras,
        shares_clock_with=data.slaves,
        software_synced=data.software,
    )
    try:
        result = fit_take(end)
    except SyncError as exc:
        return end, None, f"sync failed: {exc}"
    # A device that recorded nothing has no times to map: it neither needs a fit nor may it
    # fail the take (its datasets stay empty, the report says so).
    holding = {n for n, k in data.frames.items() if k} | {n for n, k in data.events.items() if k}
    tied = [
        d
        for name, d in result.report.devices.items()
        if name in holding and (d.clock_from != "host" or d.sync == "software")
    ]
    if holding and not tied:
        why = "; ".join(result.report.warnings[:3])
        return end, None, f"no device clock could be fitted to the trigger pulses ({why})"
    return end, result, None


# -- sealing -------------------------------------------------------------------------------
def _finalize_crashed(
    path: Path, rr: RecoveryReport, data: TakeData, trims: list[Trim], *, dry_run: bool
) -> RecoveryReport:
    """A take that died while recording (or before finalize): sync from the file, seal."""
    journal = data.journal or {}
    jl = journal_losses(journal, rr.warnings)
    rr.journal_losses = len(jl)
    rr.losses_added = [*_trim_losses(trims), *_crash_losses(data)]
    end, result, reason = _fit(data, [*jl, *rr.losses_added])
    rr.warnings.append(_crash_note(data))
    failed = data.status == Status.FAILED
    if failed:
        rr.reason = f"marked failed by its writer: {data.failure_reason}"
    if end is not None and result is not None:
        book = Bookkeeping.from_journal(journal, rr.warnings)
        notes = [*data.warnings, f"{_crash_note(data)}; sealed by `rigd recover`"]
        seal = Seal.fitted(end, result, book, active_until="the crash", notes=notes)
        rr.outcome = "would_seal" if dry_run else "sealed"
    else:
        rr.reason = f"{rr.reason}; {reason}" if failed else reason
        rr.outcome = "would_seal_failed" if dry_run else "sealed_failed"
        seal = Seal.failed(
            f"{data.failure_reason}; recovered but not finalized: {reason}"
            if failed
            else f"recovered after a crash of its writer but not finalized: {reason}"
        )
    if dry_run:
        return rr
    with _resumed(path, data.writer_config, trims) as w:
        seal_take(w, seal, recovery=partial(_stamped, rr), keep_failure_reason=failed)
    log.warning("%s", rr.line())
    return rr


def _stamped(rr: RecoveryReport, status: str) -> str:
    """The recovery report the sealed take stores, with the status it reached."""
    rr.status_after = status
    return rr.model_dump_json()


@contextmanager
def _resumed(path: Path, config: WriterConfig, trims: list[Trim] | None = None) -> Iterator[TakeWriter]:
    """The take reopened for sealing (closed afterwards); with `trims`, the repair it applies
    must be the one that was checked, else the take changed meanwhile."""
    w = resume_take(path, config, extend_truncated=True)
    try:
        if trims is not None and w.state.repairs != trims:
            raise TakeError(f"{path}: the take changed while it was being recovered; run recovery again")
        yield w
    finally:
        w.close()


def _trim_losses(trims: list[Trim]) -> list[LossRecord]:
    """Loss records for what the repair had to cut (only trims that lost recorded items)."""
    return [
        LossRecord(
            device=t.device,
            what=t.what,
            count=t.lost,
            reason=f"cut by crash recovery ({t.hpath}): {t.reason}",
        )
        for t in trims
        if t.lost > 0
    ]


def _continue_finalize(path: Path, rr: RecoveryReport, data: TakeData, *, dry_run: bool) -> RecoveryReport:
    """A take whose finalize a crash cut short: finish it with the plan it started with."""
    rr.finalize_resumed = True
    note = (
        "finalize was interrupted by a crash and completed by `rigd recover` with the clock maps "
        "it had started with (times identical to an uninterrupted finalize)"
    )
    rr.warnings.append(note)
    report = data.stored_report
    if report is not None:
        report = report.model_copy(deep=True)
        report.warnings.append(note)
    rr.outcome = "would_seal" if dry_run else "sealed"
    if dry_run:
        return rr
    with _resumed(path, data.writer_config) as w:
        seal_take(w, Seal.resumed(report), recovery=partial(_stamped, rr))
    log.warning("%s", rr.line())
    return rr


def _repair_only(path: Path, rr: RecoveryReport, trims: list[Trim], *, dry_run: bool) -> RecoveryReport:
    """A take its writer marked failed that a failed write left truncated: make it readable
    (extend, trim what was never written) and keep its status and reason."""
    rr.trims = trims
    rr.reason = "marked failed by its writer; only repaired so that it opens"
    rr.outcome = "would_seal_failed" if dry_run else "sealed_failed"
    rr.losses_added = _trim_losses(trims)
    if dry_run:
        return rr
    with _resumed(path, WriterConfig(), trims) as w:
        rr.status_after = "failed"
        state = w.state
        rr.frames.update((name, cam.stats.items) for name, cam in state.cameras.items())
        rr.events.update((name, store.stats.items) for name, store in state.stores.items())
        rr.pulses = state.pulses.stats.items
        mark_recovered(w, rr.model_dump_json())
    log.warning("%s", rr.line())
    return rr


def _seal_unresumable(path: Path, rr: RecoveryReport, reason: str, *, dry_run: bool) -> RecoveryReport:
    """Mark failed with the reason and nothing else: no data is trimmed or rewritten."""
    rr.reason = reason
    rr.outcome = "would_seal_failed" if dry_run else "sealed_failed"
    if dry_run:
        return rr
    with open_h5(path, "r+") as f:
        old = f.attrs.get(Root.FAILURE_REASON)
        rr.failure_reason_before = None if old is None else attr_text(old)
        f.attrs[Root.STATUS] = Status.FAILED
        f.attrs[Root.FAILURE_REASON] = reason if old is None else f"{attr_text(old)}; {reason}"
        f.attrs[Root.RECOVERED_UTC] = utc_now()
        rr.status_after = "failed"
        f.attrs[Root.RECOVERY_REPORT] = rr.model_dump_json()
    log.warning("%s", rr.line())
    return rr
