"""Whether a take holds everything its rig recorded: the verdict every summary shows first.

`status` says where the file is in its lifecycle (`complete` = sealed, times in rig time); it
does not say whether data was lost on the way. The verdict does: a sealed take that lost
anything (a loss record, a pulse a device missed, a dropped frame, a device that recorded
nothing, the pulses a recovery could not save) is `degraded`, with one reason per loss. It is
computed from what every take already stores (the sync report, the device groups, the status
attributes), not stored itself, so takes written before the verdict existed get one too.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from rigd.core.schema import LossRecord, SyncReport

Verdict = Literal["complete", "degraded", "failed", "unfinished", "damaged"]

#: Reasons a one-line display shows before it says how many more there are.
LINE_REASONS = 4


class TakeVerdict(BaseModel):
    """The verdict on a take and, unless it is `complete`, why."""

    model_config = ConfigDict(extra="forbid")

    verdict: Verdict = Field(
        description="complete: sealed and nothing lost; degraded: sealed, but it lost data (reasons); "
        "failed: it failed and cannot be used as a take; unfinished: `rigd recover` must seal it first; "
        "damaged: the file breaks the take format's rules (docs/take-format.md) and is not read."
    )
    reasons: list[str] = Field(default_factory=list)

    @property
    def ok(self) -> bool:
        """Whether the take holds everything (what `--strict` asks for)."""
        return self.verdict == "complete"

    def line(self, limit: int = LINE_REASONS) -> str:
        """`degraded — reason; reason; ... (+N more)`, or `complete — nothing lost`."""
        if not self.reasons:
            return f"{self.verdict} — nothing lost" if self.ok else self.verdict
        shown = "; ".join(self.reasons[:limit])
        more = len(self.reasons) - limit
        return f"{self.verdict} — {shown}" + (f" (+{more} more)" if more > 0 else "")


def _plural(n: int, word: str) -> str:
    return f"{n:,} {word}" if n == 1 else f"{n:,} {word}s"


def _loss_reasons(losses: list[LossRecord]) -> list[str]:
    """One reason per (device, kind of item) lost; a count of 0 in a record means the count is
    unknown, still a loss (the records that say so name the span or the counters to look at)."""
    groups: dict[tuple[str, str], list[LossRecord]] = {}
    for rec in losses:
        groups.setdefault((rec.device, rec.what), []).append(rec)
    out = []
    for (device, what), recs in groups.items():
        known = sum(r.count for r in recs)
        unknown = any(r.count == 0 for r in recs)
        if known and unknown:
            amount = f"{known:,} {what} and more (count partly unknown) lost"
        elif known:
            amount = f"{known:,} {what} lost"
        else:
            amount = f"{what} lost (count unknown)"
        records = f" ({len(recs)} loss records)" if len(recs) > 1 else ""
        out.append(f"{device}: {amount}{records}")
    return out


def loss_reasons(
    report: SyncReport | None,
    frames: Mapping[str, int],
    events: Mapping[str, int],
    *,
    recovered_utc: str | None = None,
    failure_reason: str | None = None,
) -> list[str]:
    """Everything a sealed take lost, one short reason each (empty: it holds everything).

    `frames` / `events`: what each camera and event sensor holds in the take (a device that
    recorded none is a loss even where no record says why). `recovered_utc` / `failure_reason`:
    a take `rigd recover` sealed after a crash or after its writer failed it."""
    reasons: list[str] = []
    if recovered_utc is not None:
        why = f" after its writer failed it ({failure_reason})" if failure_reason else " after a crash"
        reasons.append(f"recovered{why} at {recovered_utc}: data after its last flush is lost")
    elif failure_reason:
        reasons.append(f"its writer recorded a failure: {failure_reason}")
    if report is None:
        reasons.append("no sync report: what the take lost is unknown")
    for counts, unit in ((frames, "frames"), (events, "events")):
        reasons.extend(f"{name}: recorded no {unit}" for name, n in counts.items() if n == 0)
    if report is not None:
        if report.pulses_missing_from_box_log:
            n = len(report.pulses_missing_from_box_log)
            reasons.append(f"trigger: {_plural(n, 'pulse')} missing from the box's log")
        for name, dev in report.devices.items():
            if dev.missing_pulses:
                reasons.append(f"{name}: {len(dev.missing_pulses):,} of {report.n_pulses:,} pulses missing")
            if dev.dropped_frames:
                reasons.append(f"{name}: {_plural(len(dev.dropped_frames), 'frame')} dropped")
        reasons.extend(_loss_reasons(report.losses))
    return reasons


def take_verdict(
    status: str,
    report: SyncReport | None,
    frames: Mapping[str, int],
    events: Mapping[str, int],
    *,
    recovered_utc: str | None = None,
    failure_reason: str | None = None,
) -> TakeVerdict:
    """The verdict on a take with this status, sync report and device counts (see `loss_reasons`)."""
    if status == "recording":
        return TakeVerdict(
            verdict="unfinished",
            reasons=["still recording, or its writer stopped before sealing it: run `rigd recover`"],
        )
    if status != "complete":
        why = failure_reason or "no reason recorded"
        return TakeVerdict(verdict="failed", reasons=[why if status == "failed" else f"status {status!r}"])
    reasons = loss_reasons(report, frames, events, recovered_utc=recovered_utc, failure_reason=failure_reason)
    return TakeVerdict(verdict="degraded" if reasons else "complete", reasons=reasons)


def damaged_verdict(problems: list[str]) -> TakeVerdict:
    """The verdict on a file that breaks the take format's rules (a `TakeFormatError`, or
    problems `validate_take` found): whatever else it says is not to be trusted."""
    return TakeVerdict(verdict="damaged", reasons=problems or ["breaks the take format (no detail)"])
