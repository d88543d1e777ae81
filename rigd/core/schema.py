"""The take file schema: version, HDF5 layout names, and the sync report model.

The layout is documented in docs/take-format.md; this module is its single source in code,
so the writer, the reader and the validator cannot drift apart.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

SCHEMA_NAME = "rigd.take"
#: Major changes break readers; minor ones only add datasets or attributes.
#: 1.1 added `events/<sensor>/trigger/host_time_ns`, the flush journal and the crash-recovery
#: attributes; 1.0 takes stay readable (see `added_in`).
SCHEMA_VERSION = "1.2"

EVENTS_GROUP = "events"
FRAMES_GROUP = "frames"
TRIGGER_GROUP = "trigger"
SYNC_GROUP = "sync"
CONFIG_DATASET = "config_json"
#: uint8 (2, capacity): two slots, overwritten in place alternately on every flush given a
#: journal (the capture's loss bookkeeping), each `{"flush": n, "journal": {...}}` as UTF-8 JSON
#: padded with NUL bytes. The newest slot that parses is current; the other survives a kill
#: in the middle of a write.
JOURNAL_DATASET = "journal_json"
#: Root attr (JSON) written when finalize starts: clock maps and t_offset, so a finalize cut
#: short by a crash is continued with exactly the same mapping. Removed once complete.
FINALIZE_PLAN_ATTR = "finalize_plan_json"
#: Sensor group attr: events [0, t_rig_upto) of `t` already hold rig time - t_offset.
FINALIZE_UPTO_ATTR = "t_rig_upto"
#: Sensor dataset: redo log of the block being rewritten (attr `range` = [start, stop)).
FINALIZE_SCRATCH = "finalize_scratch"
#: Sensor datasets `tail_<x|y|p|t>` (2 slots, one chunk long) holding the flushed events past
#: the last whole chunk while recording, and attr `tail_meta` ([[first row, rows]] per slot).
TAIL_PREFIX = "tail_"
TAIL_META_ATTR = "tail_meta"
#: An event sensor group's attr saying how its events are stored (absent: "columns", x/y/p/t).
EVENT_STORAGE_ATTR = "storage"
#: Datasets of an "evt_words" sensor (schema 1.2): the EVT words as sent, and one row per
#: stored block of them (where, how many events, times, and the decoder state to start from).
EVT_WORDS = "evt_words"
EVT_INDEX = "evt_index"
#: The first columns of `evt_index`; the decoder state of the sensor's format follows.
#: `follows`: 1 when the row's bytes continue the previous row's in the sensor's stream (nothing
#: refused or lost between, the same shift), so the two decode as one piece.
EVT_INDEX_COLUMNS = ("byte_start", "byte_len", "events", "t_first", "t_last", "shift_us", "follows")
#: Root attrs of a take sealed by `rigd recover` (ISO time; JSON RecoveryReport).
RECOVERED_ATTR = "recovered_utc"
END_REASON_ATTR = "end_reason"
RECOVERY_REPORT_ATTR = "recovery_report_json"
#: Root attrs of a captured take (int64 rig us): its trigger window, [start, end), and the
#: margin before the first pulse it starts with; `window_outside_json` (JSON): per device,
#: what arrived outside the window and was not written ({"before", "after", "triggers_before",
#: "triggers_after"}; events or frames).
WINDOW_START_ATTR = "window_start_us"
WINDOW_END_ATTR = "window_end_us"
WINDOW_MARGIN_ATTR = "window_margin_us"
WINDOW_OUTSIDE_ATTR = "window_outside_json"

ROOT_ATTRS = ("schema", "schema_version", "status", "take_id", "created_utc", "rigd_version", "time_domain")
#: `events/<sensor>/<name>`: p is stored as uint8 1/0 (DSEC), not the in-memory int8 +1/-1.
#: Dtypes by name (numpy accepts the names; this module imports no numpy, so `rigd status` and the
#: other clients of the daemon's protocol start without it).
EVENT_DTYPES: dict[str, str] = {"x": "uint16", "y": "uint16", "p": "uint8", "t": "int64"}
#: `events/<sensor>/trigger/<name>`
TRIGGER_DTYPES: dict[str, str] = {
    "t": "int64",
    "p": "uint8",
    "channel": "uint8",
    "t_device": "int64",
    # Host monotonic ns when the packet carrying the edge arrived; -1 unknown (schema 1.1).
    "host_time_ns": "int64",
}
#: Items newer than 1.0, with the schema version that added them: takes of an older minor
#: version may lack them, and readers treat a missing one as "unknown".
ADDED_IN: dict[str, tuple[int, int]] = {"trigger/host_time_ns": (1, 1)}
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


def encode_journal(flush: int, journal: Any) -> bytes:
    """One journal slot's content (UTF-8 JSON, no NUL bytes)."""
    return json.dumps({"flush": flush, "journal": journal}, allow_nan=True).encode("utf-8")


def decode_journal(slots: NDArray[np.uint8]) -> tuple[int, dict[str, Any]] | None:
    """(flush number, journal) of the newest slot that parses; None if none does."""
    import numpy as np

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
