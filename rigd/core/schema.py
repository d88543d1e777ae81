"""The take file schema: its version, what each minor version added, the journal slots' coding,
and the sync report model.

The layout's names are in `rigd.core.layout`; docs/take-format.md is the contract for both.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from rigd.core.kinds import SensorKind
from rigd.core.layout import Events, TriggerEdges

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

SCHEMA_NAME = "rigd.take"
#: Major changes break readers; minor ones only add datasets or attributes.
#: 1.1 added `events/<sensor>/trigger/host_time_ns`, the flush journal and the crash-recovery
#: attributes; 1.0 takes stay readable (see `added_in`).
SCHEMA_VERSION = "1.2"

#: Items newer than 1.0, with the schema version that added them: takes of an older minor
#: version may lack them, and readers treat a missing one as "unknown".
ADDED_IN: dict[str, tuple[int, int]] = {f"{Events.TRIGGER}/{TriggerEdges.HOST_TIME_NS}": (1, 1)}

LossKind = Literal["frames", "events", "triggers", "pulses"]


def encode_journal(flush: int, journal: Any) -> bytes:
    """One journal slot's content (UTF-8 JSON, no NUL bytes)."""
    return json.dumps({"flush": flush, "journal": journal}, allow_nan=True).encode("utf-8")


def decode_journal(slots: NDArray[np.uint8]) -> tuple[int, dict[str, Any]] | None:
    """(flush number, journal) of the newest slot that parses; None if none does."""
    import numpy as np  # here, so the protocol's clients (`rigd status`) start without numpy

    best: tuple[int, dict[str, Any]] | None = None
    for row in np.atleast_2d(np.asarray(slots, dtype=np.uint8)):
        text = row.tobytes().split(b"\0", 1)[0]
        try:
            data = json.loads(text)
        except (json.JSONDecodeError, UnicodeDecodeError):
            continue  # an empty slot, or one a kill cut in the middle of its write
        if (
            isinstance(data, dict)
            and isinstance(data.get("flush"), int)
            and isinstance(data.get("journal"), dict)
            and (best is None or data["flush"] > best[0])
        ):
            best = (data["flush"], data["journal"])
    return best


def parse_version(version: str) -> tuple[int, int]:
    """(major, minor) of a "MAJOR.MINOR" schema version; (-1, -1) when it does not parse."""
    major, _, minor = version.partition(".")
    try:
        return int(major), int(minor or 0)
    except ValueError:
        return -1, -1


def has_item(version: str, item: str) -> bool:
    """Whether a take of schema `version` must have `item` (a key of ADDED_IN, or anything older)."""
    return parse_version(version) >= ADDED_IN.get(item, (1, 0))


class DeviceSync(BaseModel):
    """How one device clock was tied to the rig clock, and what it missed."""

    model_config = ConfigDict(extra="forbid", ser_json_inf_nan="constants")

    device: str
    kind: SensorKind
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
