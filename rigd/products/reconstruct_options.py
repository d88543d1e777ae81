"""What `rigd reconstruct` is asked (takes, output, scheduler, every knob with the paper values as
defaults) and what it answers per take.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from reconstruction.partition import PartitionConfig
from rigd.products.reconstruct_scheduler import check_scheduler
from rigd.products.reconstruct_tasks import FilterKnobs


class ReconstructOptions(BaseModel):
    """Takes to reconstruct, where to, on which scheduler, and every knob (paper values as defaults)."""

    model_config = ConfigDict(frozen=True)

    takes: list[Path]
    out: Path
    scheduler: str | None = None
    """None or "threads": local threads; "processes"; "sync" (one thread); else a distributed address."""

    @field_validator("scheduler")
    @classmethod
    def _known_scheduler(cls, v: str | None) -> str | None:
        """A typo (`thread`) or a malformed address fails here, before any take is read."""
        return check_scheduler(v)

    workers: int | None = Field(None, ge=1)
    filter: FilterKnobs = FilterKnobs()
    partition_window_us: int = Field(5_000, ge=100)
    threshold: float = Field(2.0, gt=0)
    """Activity budget per segment, kept events per pixel of all sensors."""
    instant_weight: float = Field(1.0, ge=0)
    min_segment_us: int = Field(10_000, ge=0)
    map_scale: float = Field(0.25, gt=0, le=1)
    max_candidates: int = Field(256, ge=0)
    """Keyframe candidates per segment at most (evenly spaced); 0: all of them."""
    keyframe_camera: str | None = None
    candidate_interval_us: int = Field(33_333, ge=1)
    """Candidate spacing in takes without cameras."""
    e2i: Literal["highpass", "direct"] = "highpass"
    contrast: float = Field(0.3, gt=0)
    cutoff_hz: float = Field(5.0, gt=0)
    block_events: int = Field(1 << 20, ge=1024)

    def partition_config(self) -> PartitionConfig:
        return PartitionConfig(
            window_us=self.partition_window_us,
            threshold=self.threshold,
            instant_weight=self.instant_weight,
            min_segment_us=self.min_segment_us,
            map_scale=self.map_scale,
        )


class SensorReconstruction(BaseModel):
    """What denoising kept of one sensor's events."""

    events_in: int
    events_kept: int


class TakeReconstruction(BaseModel):
    """One take's outcome; `take` is the path as given, `error` one line when it failed."""

    take: str
    segments: int = 0
    sensors: dict[str, SensorReconstruction] = {}
    seconds: float = 0.0
    error: str | None = None
