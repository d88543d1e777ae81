"""The take file schema: version, HDF5 layout names, and the sync report model.

The layout is documented in docs/take-format.md; this module is its single source in code,
so the writer, the reader and the validator cannot drift apart.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

SCHEMA_NAME = "rigd.take"
#: Major changes break readers; minor ones only add datasets or attributes.
SCHEMA_VERSION = "1.0"

EVENTS_GROUP = "events"
FRAMES_GROUP = "frames"
TRIGGER_GROUP = "trigger"
SYNC_GROUP = "sync"
CONFIG_DATASET = "config_json"

ROOT_ATTRS = ("schema", "schema_version", "status", "take_id", "created_utc", "rigd_version", "time_domain")
#: `events/<sensor>/<name>`: p is stored as uint8 1/0 (DSEC), not the in-memory int8 +1/-1.
EVENT_DTYPES: dict[str, type[np.generic]] = {"x": np.uint16, "y": np.uint16, "p": np.uint8, "t": np.int64}
#: `events/<sensor>/trigger/<name>`
TRIGGER_DTYPES: dict[str, type[np.generic]] = {
    "t": np.int64,
    "p": np.uint8,
    "channel": np.uint8,
    "t_device": np.int64,
}
#: `frames/<camera>/<name>`, all int64, one entry per frame.
FRAME_SERIES = (
    "t_exposure_start_us",
    "t_exposure_start_device_us",
    "exposure_us",
    "frame_counter",
    "pulse_index",
    "host_time_ns",
)
#: `trigger/pulses/<name>`, all int64.
PULSE_SERIES = ("index", "t_us", "host_time_ns")

LossKind = Literal["frames", "events", "triggers", "pulses"]


class DeviceSync(BaseModel):
    """How one device clock was tied to the rig clock, and what it missed."""

    model_config = ConfigDict(extra="forbid", ser_json_inf_nan="constants")

    device: str
    kind: Literal["rgb_camera", "event_sensor"]
    device_ref_us: int
    rig_ref_us: int
    rate: float
    frac_us: float = 0.0
    drift_ppm: float = Field(description="Device clock rate against the rig clock, ppm (+: device fast).")
    n_matched: int = Field(description="Pulses this device saw and that were matched to a box pulse.")
    residual_rms_us: float
    residual_max_us: float
    missing_pulses: list[int] = Field(
        default_factory=list, description="Box pulse indices this device has no observation of."
    )
    dropped_frames: list[int] = Field(
        default_factory=list,
        description="Frame counter values missing from the delivered frames (lost in device or transport).",
    )
    unmatched_observations: int = Field(
        0, description="Device trigger observations (frames / trigger-in edges) matched to no box pulse."
    )
    shares_clock_with: str | None = Field(
        None, description="Master whose clock this device runs on (camera synchronization), if any."
    )
    sync: Literal["hardware", "software"] = Field(
        "hardware",
        description="software: a free-running device stamped by the host clock; its times are mapped "
        "through the host-to-rig fit (millisecond accuracy) and its frames go to the nearest pulse.",
    )
    clock_from: Literal["own_pulses", "master", "host"] = Field(
        "own_pulses", description="What the map was fitted on: its own pulses, its master's, the host clock."
    )


class LossRecord(BaseModel):
    """Data the host lost or refused; never dropped without one of these."""

    model_config = ConfigDict(extra="forbid")

    device: str
    what: LossKind
    count: int
    reason: str
    t_first_us: int | None = Field(None, description="Device time of the first lost item, when known.")
    t_last_us: int | None = None


class SyncReport(BaseModel):
    """The take's sync report: rig timebase facts, per-device fits, and all losses."""

    # NaN marks "not fitted"; keep it a NaN through JSON instead of turning it into null.
    model_config = ConfigDict(extra="forbid", ser_json_inf_nan="constants")

    schema_version: str = SCHEMA_VERSION
    rate_hz: float
    n_pulses: int = Field(description="Pulses the trigger box reported emitting.")
    t_first_pulse_us: int | None
    t_last_pulse_us: int | None
    pulses_missing_from_box_log: list[int] = Field(
        default_factory=list, description="Pulse indices absent from the box's reported timestamps."
    )
    pulses_seen_by_no_device: list[int] = Field(
        default_factory=list, description="Pulses the box reported but no device observed."
    )
    devices: dict[str, DeviceSync] = Field(default_factory=dict)
    losses: list[LossRecord] = Field(default_factory=list)
    device_counters: dict[str, dict[str, int]] = Field(
        default_factory=dict, description="Each device's own counters at the end (delivered, dropped, ...)."
    )
    trigger_link: dict[str, int] = Field(
        default_factory=dict, description="Counters of the host-trigger box link (corrupt lines, retries)."
    )
    warnings: list[str] = Field(default_factory=list)
