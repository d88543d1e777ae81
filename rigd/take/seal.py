"""Sealing a take: fit every device clock to the pulses, write the report, close the take for good.

A take ends two ways: the capture pipeline finalizes it with what it holds in memory (its
channels' observations, the loss ledger, the fault board), and `rigd recover` seals one whose
writer died with what it rebuilds from the file and the last flush's journal. Both describe
what they know as a `TakeEnd` and a `Bookkeeping`, and both close the take through `seal_take`,
so the steps and their order -- fit, report (losses, counters, warnings, trigger link), window,
end reason, recovery stamp, finalize (clock maps, pulse indices, redo-logged rewrite of the
times, status) or fail -- exist once.

The steps themselves live here too, as functions of the writer's open state (the writer only
records): `finalize_take` (crash-safe: the plan is stored first and every block of event times
goes through a redo log, `rigd.take.finalize`), `continue_finalize` (a take `rigd.take.resume`
reopened mid-finalize), `fail_take`, `mark_recovered`, `set_window` and `set_end_reason`.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import TypeAdapter, ValidationError

from rigd.core.errors import TakeError
from rigd.core.layout import Root, Status
from rigd.core.schema import LossRecord, SyncReport
from rigd.core.timebase import ClockMap
from rigd.sync import DeviceObservations, PulseLog, SyncResult, synchronize
from rigd.take.finalize import FinalizePlan, Finalizer
from rigd.take.h5file import as_oserror, utc_now
from rigd.take.refused import no_room_to_flush
from rigd.take.take_state import TakeState
from rigd.take.units import label_tree
from rigd.take.writer import TakeWriter

log = logging.getLogger(__name__)

_COUNTERS = TypeAdapter(dict[str, dict[str, int]])
_LINK = TypeAdapter(dict[str, int])


@dataclass(slots=True)
class TakeEnd:
    """What the sync engine needs at the end of a take, however it was learned."""

    pulses: PulseLog
    observations: list[DeviceObservations]
    rate_hz: float
    #: Every loss record so far: the fit puts them in the report.
    losses: list[LossRecord]
    cameras: list[str]
    shares_clock_with: Mapping[str, str] = field(default_factory=dict)
    software_synced: set[str] = field(default_factory=set)


@dataclass(slots=True)
class Bookkeeping:
    """The take's bookkeeping besides its losses: the capture's ledger and fault board, or the
    journal of its last flush."""

    device_counters: dict[str, dict[str, int]] = field(default_factory=dict)
    trigger_link: dict[str, int] = field(default_factory=dict)
    written_off: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    fault_history: list[str] = field(default_factory=list)
    faults_active: list[str] = field(default_factory=list)

    def report_warnings(self, active_until: str) -> list[str]:
        """Its lines for the sync report; `active_until` says when the active faults were
        seen last ("the end", "the crash")."""
        return [
            *(f"{name} failed mid-take and was written off: {why}" for name, why in self.written_off.items()),
            *self.warnings,
            *self.fault_history,
            *(f"{line} (still active at {active_until})" for line in self.faults_active),
        ]

    @classmethod
    def from_journal(cls, journal: Mapping[str, Any], problems: list[str]) -> Bookkeeping:
        """From a flush journal (`LossLedger.journal`); what does not parse is left out and
        said in `problems`, never an error (bookkeeping must not stop a recovery)."""
        book = cls()
        for key, adapter in (("device_counters", _COUNTERS), ("trigger_link", _LINK)):
            if key not in journal:
                continue
            try:
                setattr(book, key, adapter.validate_python(journal[key]))
            except ValidationError as exc:
                problems.append(f"journal {key!r} unreadable ({exc.error_count()} error(s)); ignored")
        failed = journal.get("failed_devices", {})
        if isinstance(failed, dict):
            book.written_off = {str(name): str(why) for name, why in failed.items()}
        for key, attr in (
            ("warnings", "warnings"),
            ("fault_history", "fault_history"),
            ("faults", "faults_active"),
        ):
            items = journal.get(key, [])
            if isinstance(items, list):
                setattr(book, attr, [str(item) for item in items])
            else:
                problems.append(f"journal {key!r} is not a list; ignored")
        return book


def journal_losses(journal: Mapping[str, Any], problems: list[str]) -> list[LossRecord]:
    """The loss records of a flush journal; one that does not parse is said in `problems`."""
    raw = journal.get("losses", [])
    if not isinstance(raw, list):
        problems.append("journal 'losses' is not a list; ignored")
        return []
    out = []
    for i, item in enumerate(raw):
        try:
            out.append(LossRecord.model_validate(item))
        except ValidationError as exc:
            problems.append(f"journal loss record {i} unreadable ({exc.error_count()} error(s)); ignored")
    return out


def fit_take(end: TakeEnd) -> SyncResult:
    """Every device clock fitted to the pulses (raises SyncError when the engine cannot)."""
    return synchronize(
        end.pulses,
        end.observations,
        end.rate_hz,
        end.losses,
        shares_clock_with=dict(end.shares_clock_with),
        software_synced=end.software_synced,
    )


@dataclass(frozen=True, slots=True)
class Seal:
    """How a take is to be closed: finalized with a fit, its cut-short finalize continued, or
    marked failed with a reason. Built by `fitted`, `resumed` or `failed`."""

    how: Literal["finalize", "continue", "fail"]
    report: SyncReport | None = None
    maps: dict[str, ClockMap] = field(default_factory=dict)
    frame_pulse_index: dict[str, NDArray[np.int64]] = field(default_factory=dict)
    failure: str | None = None

    @classmethod
    def fitted(
        cls,
        end: TakeEnd,
        result: SyncResult,
        book: Bookkeeping,
        *,
        active_until: str,
        notes: Sequence[str] = (),
    ) -> Seal:
        """Finalize with this fit; the report gains the bookkeeping, then `notes`."""
        report = result.report
        report.device_counters = book.device_counters
        report.warnings.extend(book.report_warnings(active_until))
        report.warnings.extend(notes)
        report.trigger_link = book.trigger_link
        index = {name: result.observation_pulse_index[name] for name in end.cameras}
        return cls("finalize", report, dict(result.maps), index)

    @classmethod
    def resumed(cls, report: SyncReport | None) -> Seal:
        """Continue a finalize a crash cut short, with its stored plan (`report` replaces the
        stored one; None keeps it)."""
        return cls("continue", report)

    @classmethod
    def failed(cls, reason: str) -> Seal:
        """No device clock could be tied to rig time: mark the take failed, times untouched."""
        return cls("fail", failure=reason)


def seal_take(
    writer: TakeWriter,
    seal: Seal,
    *,
    window: tuple[int | None, int | None, int, Mapping[str, Mapping[str, int]]] | None = None,
    end_reason: str | None = None,
    recovery: Callable[[str], str] | None = None,
    keep_failure_reason: bool = False,
) -> str:
    """Close `writer`'s take as `seal` says; returns the status it ends with.

    `window`: the trigger window and what arrived outside it (`set_window`).
    `recovery`: the take is sealed by recovery; it is stamped `recovered_utc` first (a crash
    during the finalize below still shows it) and, once sealed, given the recovery report
    this callable returns for the status reached.
    """
    if recovery is not None:
        mark_recovered(writer, None)
    if window is not None:
        set_window(writer, *window)
    if end_reason is not None:
        set_end_reason(writer, end_reason)
    if seal.how == "finalize" and seal.report is not None:
        finalize_take(writer, seal.maps, seal.frame_pulse_index, seal.report)
    elif seal.how == "continue":
        continue_finalize(writer, seal.report)
    elif seal.how == "fail" and seal.failure is not None:
        fail_take(writer, seal.failure)
    else:
        raise TakeError(
            f"{writer.path}: a {seal.how!r} seal without its report or reason (build it with Seal.*)"
        )
    if recovery is not None:
        mark_recovered(writer, recovery(writer.status), keep_failure_reason=keep_failure_reason)
    log.debug("take %s sealed: %s (%s)", writer.path, writer.status, seal.how)
    return writer.status


# -- the steps ---------------------------------------------------------------------------
def set_end_reason(writer: TakeWriter, reason: str) -> None:
    """Why the recording ended (pulses done, an operator's stop, a fault), for whoever reads
    the take later."""
    s = writer.state
    s.check_writable()
    s.f.attrs[Root.END_REASON] = reason


def set_window(
    writer: TakeWriter,
    start_us: int | None,
    end_us: int | None,
    margin_us: int,
    outside: Mapping[str, Mapping[str, int]],
) -> None:
    """The take's trigger window in rig us (None: unknown, no pulse) and, per device, what
    arrived outside it and was not written."""
    s = writer.state
    s.check_writable()
    attrs = s.f.attrs
    for key, value in ((Root.WINDOW_START, start_us), (Root.WINDOW_END, end_us)):
        if value is not None:
            attrs[key] = np.int64(value)
    attrs[Root.WINDOW_MARGIN] = np.int64(margin_us)
    attrs[Root.WINDOW_OUTSIDE] = json.dumps({k: dict(v) for k, v in outside.items()}, sort_keys=True)


def finalize_take(
    writer: TakeWriter,
    maps: dict[str, ClockMap],
    frame_pulse_index: dict[str, NDArray[np.int64]],
    report: SyncReport,
) -> None:
    """Map every stored time to rig time, build the DSEC index and mark the take complete.

    Crash-safe: the maps and t_offset are stored first (`finalize_plan_json`), then each
    block of event times goes through a redo log and a progress attr, so a take whose
    process died here is finished by `resume_take` + `continue_finalize` with identical times.
    """
    s = writer.state
    if s.plan is not None:
        raise TakeError(f"{s.path}: finalize already started; call continue_finalize()")
    s.check_writable()
    s.write_all()
    s.drop_tails()
    label_tree(s.f)  # units and compression filters named for plain HDF5 users
    s.f.flush()
    finalizer = s.finalizer()
    plan = finalizer.plan(maps, frame_pulse_index, report)
    finalizer.start(plan, frame_pulse_index, report)
    s.plan = plan
    s.status = "finalizing"
    _run_finalize(s, finalizer, plan)


def continue_finalize(writer: TakeWriter, report: SyncReport | None = None) -> None:
    """Finish a finalize that a crash cut short, with the maps and t_offset it started with.

    `report` replaces the stored sync report (recovery adds its notes); the mapping never
    changes, so the result is the same as an uninterrupted finalize.
    """
    s = writer.state
    s.check_open()
    if s.plan is None or s.status != "finalizing":
        raise TakeError(f"{s.path}: no interrupted finalize to continue (status {s.status})")
    finalizer = s.finalizer()
    if report is not None:
        finalizer.write_sync(s.plan.maps, report)
    _run_finalize(s, finalizer, s.plan)


def _run_finalize(s: TakeState, finalizer: Finalizer, plan: FinalizePlan) -> None:
    finalizer.run(plan)
    s.status = "complete"
    finalizer.drop_bookkeeping()
    log.info("take %s finalized (t_offset %d us)", s.path, plan.t_offset)


def mark_recovered(
    writer: TakeWriter, recovery_report_json: str | None, *, keep_failure_reason: bool = False
) -> None:
    """Stamp a take sealed by recovery (`recovered_utc`, and the report once known).

    A take that a crashed finalize had marked failed and that is now complete drops its
    stale `failure_reason`; the recovery report keeps it. `keep_failure_reason`: the
    take's own writer failed it (disk full) before finalize; sealed `complete`, it keeps
    the reason, so readers see both that it is usable and why it is short.
    """
    s = writer.state
    s.check_open()
    f = s.f
    if Root.RECOVERED_UTC not in f.attrs:
        f.attrs[Root.RECOVERED_UTC] = utc_now()
    if recovery_report_json is not None:
        f.attrs[Root.RECOVERY_REPORT] = recovery_report_json
    if s.status == "complete" and Root.FAILURE_REASON in f.attrs and not keep_failure_reason:
        del f.attrs[Root.FAILURE_REASON]
    f.flush()


def fail_take(writer: TakeWriter, reason: str) -> None:
    """Mark the take failed with a reason; everything written so far stays readable.

    Writes what is buffered, then the status, and flushes; a write that fails (disk full)
    is raised afterwards as OSError, anything else as it was. Where the file refuses the
    buffered writes, or the disk has too little room (rigd.take.refused), nothing more
    is written: the take stays as last flushed (`rigd recover` seals it) and closing the
    writer writes nothing either.
    """
    s = writer.state
    s.check_open()
    if s.status == "complete":
        log.warning("take %s: fail(%r) after finalize ignored", s.path, reason)
        return
    error: Exception | None = None
    recording = s.status == "recording"
    try:
        s.syncer.wait()
        if recording:
            s.write_all()
    except Exception as exc:  # noqa: BLE001 - raised below, once the status is set
        error = exc
    s.status = "failed"
    refused = isinstance(error, OSError | RuntimeError)
    if not refused and (no_room := no_room_to_flush(s.path)) is not None:
        error, refused = no_room, True
    if not refused:
        try:
            if recording:
                s.drop_tails_after_flush()
            s.f.attrs[Root.STATUS] = Status.FAILED
            s.f.attrs[Root.FAILURE_REASON] = reason
            s.f.flush()
        except (OSError, RuntimeError) as exc:
            error = error or exc
            refused = True
    if refused:
        # The file refuses writes even now (no room freed, a size limit), or the disk has no
        # room for the metadata: the take stays as last flushed, no flush tried (refused.py).
        assert error is not None
        s.refused = as_oserror(error)
        log.error(
            "take %s marked failed (%s); the file refuses writes: it stays as last flushed",
            s.path,
            reason,
        )
        raise s.refused from error
    log.error("take %s marked failed: %s", s.path, reason)
    if error is not None:
        raise error
