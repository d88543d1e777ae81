"""Sealing a take: fit every device clock to the pulses, write the report, close the take for good.

A take ends two ways: the capture pipeline finalizes it with what it holds in memory (its
channels' observations, the loss ledger, the fault board), and `rigd recover` seals one whose
writer died with what it rebuilds from the file and the last flush's journal. Both describe
what they know as a `TakeEnd` and a `Bookkeeping`, and both close the take through `seal_take`,
so the steps and their order -- fit, report (losses, counters, warnings, trigger link), window,
end reason, recovery stamp, finalize (clock maps, pulse indices, redo-logged rewrite of the
times, status) or fail -- exist once. Finalize's own crash safety is `TakeWriter.finalize`'s.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import TypeAdapter, ValidationError

from rigd.core.errors import TakeError
from rigd.core.schema import LossRecord, SyncReport
from rigd.core.timebase import ClockMap
from rigd.sync import DeviceObservations, PulseLog, SyncResult, synchronize
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

    `window`: the trigger window and what arrived outside it (`TakeWriter.set_window`).
    `recovery`: the take is sealed by recovery; it is stamped `recovered_utc` first (a crash
    during the finalize below still shows it) and, once sealed, given the recovery report
    this callable returns for the status reached.
    """
    if recovery is not None:
        writer.mark_recovered(None)
    if window is not None:
        writer.set_window(*window)
    if end_reason is not None:
        writer.set_end_reason(end_reason)
    if seal.how == "finalize" and seal.report is not None:
        writer.finalize(seal.maps, seal.frame_pulse_index, seal.report)
    elif seal.how == "continue":
        writer.continue_finalize(seal.report)
    elif seal.how == "fail" and seal.failure is not None:
        writer.fail(seal.failure)
    else:
        raise TakeError(
            f"{writer.path}: a {seal.how!r} seal without its report or reason (build it with Seal.*)"
        )
    if recovery is not None:
        writer.mark_recovered(recovery(writer.status), keep_failure_reason=keep_failure_reason)
    log.debug("take %s sealed: %s (%s)", writer.path, writer.status, seal.how)
    return writer.status
