"""What `Take.summary` reports: counts, rates and sync quality per device and for the take."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from rigd.core.schema import LossRecord
from rigd.take.manifest import PartEntry
from rigd.take.verdict import TakeVerdict, Verdict


class CameraSummary(BaseModel):
    model_config = ConfigDict(extra="forbid")

    frames: int
    fps: float | None = Field(description="Mean frame rate over the take (rig clock when finalized).")
    shape: list[int] = Field(description="Shape of a frame as stored (a Bayer frame: its mosaic).")
    dtype: str
    pixel_format: str = Field("rgb8", description="mono8, rgb8 or bayer_rg8 (stored as is).")
    t_first_us: int | None
    t_last_us: int | None
    dropped_frames: int | None = Field(description="Frame counter gaps from the sync report.")
    missing_pulses: int | None
    sync_rms_us: float | None
    sync_max_us: float | None


class EventSensorSummary(BaseModel):
    model_config = ConfigDict(extra="forbid")

    events: int
    event_rate_hz: float | None = Field(description="Mean events per second over the span.")
    t_first_us: int | None
    t_last_us: int | None
    span_us: int
    width: int
    height: int
    triggers: int
    missing_pulses: int | None
    sync_rms_us: float | None
    sync_max_us: float | None


class TakeSummary(BaseModel):
    """Everything a person checks first about a take, JSON-serialisable."""

    model_config = ConfigDict(extra="forbid")

    path: str
    take_id: str
    status: str
    verdict: Verdict = Field(
        "complete",
        description="complete (nothing lost), degraded (sealed but lost data), failed or unfinished; "
        "computed from the stored records (rigd.take.verdict).",
    )
    verdict_reasons: list[str] = Field(
        default_factory=list, description="Why the verdict is not complete: one reason per loss."
    )
    schema_version: str
    time_domain: str
    failure_reason: str | None = None
    recovered_utc: str | None = Field(
        None, description="Set when `rigd recover` sealed the take after its writer crashed."
    )
    end_reason: str | None = Field(
        None, description="Why the recording ended: pulses done, a stop and its reason, a fault."
    )
    cameras: dict[str, CameraSummary]
    event_sensors: dict[str, EventSensorSummary]
    pulses: int
    pulses_seen_by_no_device: list[int] = Field(default_factory=list)
    losses: list[LossRecord] = Field(default_factory=list)
    warnings: list[str] = Field(default_factory=list)
    problems: list[str] = Field(
        default_factory=list, description="Validation problems (rigd.products.inspect)."
    )
    parts: list[PartEntry] | None = Field(
        None, description="A multi-host take's parts (host, file, devices, status); None: one host."
    )

    def verdict_line(self) -> str:
        """`complete: nothing lost`, or the verdict and its first reasons (`TakeVerdict.line`)."""
        return TakeVerdict(verdict=self.verdict, reasons=self.verdict_reasons).line()
