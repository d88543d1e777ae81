"""The take file's HDF5 layout: every group, dataset and attribute name rigd writes or reads.

docs/take-format.md is the contract (what each item holds, its dtype, when it exists); this
module is its one spelling in code, so the writer, finalize, repair, recovery, the reader, the
validator and the exports cannot drift apart. It lives in `rigd.core` so that every package
(calibration and reconstruction too) may import it under the layer contracts. Renaming a value
here changes the files on disk: that is a schema change (see `rigd.core.schema`), never a
refactoring.

Names are grouped by where they sit: `Root` (the file's attributes and top-level datasets),
`Device` (attributes every device group has), `Events` (`events/<sensor>/`), `TriggerEdges`
(`events/<sensor>/trigger/`), `Frames` (`frames/<camera>/`), `Pulses` (`trigger/pulses/`),
`Sync` (`sync/`), and the values some attributes take (`Status`, `TimeDomain`, `Storage`).
"""

from __future__ import annotations

from typing import Final

#: Top-level groups.
EVENTS_GROUP: Final = "events"
FRAMES_GROUP: Final = "frames"
TRIGGER_GROUP: Final = "trigger"
SYNC_GROUP: Final = "sync"
CALIBRATION_GROUP: Final = "calibration"


# The classes below are name tables, one per place in the file: `NAME: Final = "name"` rows
# alike in shape on purpose (one spelling per name), not code to share.


class Root:
    """Attributes of `/` and the datasets at the top level."""

    SCHEMA: Final = "schema"
    SCHEMA_VERSION: Final = "schema_version"
    STATUS: Final = "status"
    TIME_DOMAIN: Final = "time_domain"
    TAKE_ID: Final = "take_id"
    CREATED_UTC: Final = "created_utc"
    FINALIZED_UTC: Final = "finalized_utc"
    RIGD_VERSION: Final = "rigd_version"
    FAILURE_REASON: Final = "failure_reason"
    FLUSH_COUNT: Final = "flush_count"
    #: Fixed-length ASCII bytes, so a flush rewrites it in place.
    LAST_FLUSH_UTC: Final = "last_flush_utc"
    FLUSH_INTERVAL_S: Final = "flush_interval_s"
    #: Present only while finalize runs, or if it was interrupted.
    FINALIZE_STARTED_UTC: Final = "finalize_started_utc"
    #: JSON written when finalize starts: clock maps and t_offset, so a finalize cut short by a
    #: crash is continued with exactly the same mapping. Removed once complete.
    FINALIZE_PLAN: Final = "finalize_plan_json"
    END_REASON: Final = "end_reason"
    #: A take sealed by `rigd recover`: when (ISO time), and its RecoveryReport (JSON).
    RECOVERED_UTC: Final = "recovered_utc"
    RECOVERY_REPORT: Final = "recovery_report_json"
    #: Only while recovery repairs a file a failed write left short.
    TRUNCATED_EOF: Final = "truncated_eof"
    #: A captured take's trigger window (int64 rig us, [start, end)) and the margin before the
    #: first pulse it starts with; `window_outside_json` (JSON): per device, what arrived
    #: outside the window and was not written ({"before", "after", "triggers_before",
    #: "triggers_after"}; events or frames).
    WINDOW_START: Final = "window_start_us"
    WINDOW_END: Final = "window_end_us"
    WINDOW_MARGIN: Final = "window_margin_us"
    WINDOW_OUTSIDE: Final = "window_outside_json"
    #: Scalar UTF-8 dataset: the rig config (RigConfig JSON).
    CONFIG: Final = "config_json"
    #: uint8 (2, capacity): two slots, overwritten in place alternately on every flush given a
    #: journal (the capture's loss bookkeeping), each `{"flush": n, "journal": {...}}` as UTF-8
    #: JSON padded with NUL bytes. The newest slot that parses is current; the other survives a
    #: kill in the middle of a write.
    JOURNAL: Final = "journal_json"
    #: A multi-host take joined from part files: JSON list, one entry per host's part (host,
    #: file, devices, sha256, size, status, verdict). Its presence makes the take a joined one,
    #: whose device groups may be external links into those files (docs/take-format.md).
    PARTS: Final = "parts_json"


class Status:
    """Values of `Root.STATUS`."""

    RECORDING: Final = "recording"
    COMPLETE: Final = "complete"
    FAILED: Final = "failed"


class TimeDomain:
    """Values of `Root.TIME_DOMAIN`."""

    DEVICE: Final = "device"
    RIG: Final = "rig"


class Device:
    """Attributes of every device group (`events/<sensor>`, `frames/<camera>`, `trigger`)."""

    WIDTH: Final = "width"
    HEIGHT: Final = "height"
    #: DeviceInfo JSON (its scalar string fields are also plain attributes: kind, spec, ...).
    INFO_JSON: Final = "info_json"
    SETTINGS_JSON: Final = "settings_json"


class Storage:
    """Values of `Events.STORAGE`."""

    COLUMNS: Final = "columns"
    EVT_WORDS: Final = "evt_words"


class Events:
    """`events/<sensor>/`: the DSEC columns, or the EVT words as sent (schema 1.2)."""

    X: Final = "x"
    Y: Final = "y"
    P: Final = "p"
    T: Final = "t"
    T_OFFSET: Final = "t_offset"
    MS_TO_IDX: Final = "ms_to_idx"
    #: Attr: `first_pulse` | `first_event` | `none`.
    T_OFFSET_SOURCE: Final = "t_offset_source"
    #: The sensor's trigger-in subgroup (names in `TriggerEdges`).
    TRIGGER: Final = "trigger"
    #: Attr saying how the events are stored (a `Storage` value; absent: columns).
    STORAGE: Final = "storage"
    #: Attr: why a sensor that sends EVT words was stored as columns.
    STORAGE_NOTE: Final = "storage_note"
    EVT_FORMAT: Final = "evt_format"
    #: The EVT words as sent, and one row per stored block of them (where, how many events,
    #: times, and the decoder state to start from).
    EVT_WORDS: Final = "evt_words"
    EVT_INDEX: Final = "evt_index"
    #: Attr of `evt_index` naming its columns.
    EVT_INDEX_COLUMNS_ATTR: Final = "columns"
    #: Attrs set on finalize of an evt_words sensor: its ClockMap as JSON, the take window it
    #: was cut to, and the stored events [first, first + count) inside that window.
    CLOCK_MAP: Final = "clock_map_json"
    WINDOW: Final = "window_us"
    FIRST_IN_WINDOW: Final = "first_in_window"
    EVENTS_IN_WINDOW: Final = "events_in_window"
    #: Datasets `tail_<x|y|p|t>` (2 slots, one chunk long) holding the flushed events past the
    #: last whole chunk while recording, and attr `tail_meta` ([[first row, rows]] per slot).
    TAIL_PREFIX: Final = "tail_"
    TAIL_META: Final = "tail_meta"
    #: The same for EVT words: bytes past the last whole chunk, `[first byte, bytes]` per slot.
    TAIL_WORDS: Final = "tail_evt_words"
    TAIL_WORDS_META: Final = "tail_words_meta"
    #: Attr while finalize runs: events [0, t_rig_upto) of `t` already hold rig time - t_offset.
    FINALIZE_UPTO: Final = "t_rig_upto"
    #: Group while finalize runs: redo log of the block being rewritten (attr `range` =
    #: [start, stop); one dataset per rewritten column with attr `segments`).
    FINALIZE_SCRATCH: Final = "finalize_scratch"
    SCRATCH_RANGE: Final = "range"
    SCRATCH_SEGMENTS: Final = "segments"


class TriggerEdges:
    """`events/<sensor>/trigger/`: the sensor's trigger-in edges."""

    T: Final = "t"
    T_DEVICE: Final = "t_device"
    P: Final = "p"
    CHANNEL: Final = "channel"
    #: Host monotonic ns when the packet carrying the edge arrived; -1 unknown (schema 1.1).
    HOST_TIME_NS: Final = "host_time_ns"


class Frames:
    """`frames/<camera>/`: the images and one int64 series entry per frame."""

    IMAGES: Final = "images"
    T_EXPOSURE_START: Final = "t_exposure_start_us"
    T_EXPOSURE_START_DEVICE: Final = "t_exposure_start_device_us"
    EXPOSURE: Final = "exposure_us"
    FRAME_COUNTER: Final = "frame_counter"
    PULSE_INDEX: Final = "pulse_index"
    HOST_TIME_NS: Final = "host_time_ns"
    CHANNELS: Final = "channels"
    DTYPE: Final = "dtype"
    PIXEL_FORMAT: Final = "pixel_format"
    BAYER_PATTERN: Final = "bayer_pattern"
    #: Attr of the timestamp series naming their unit.
    UNITS: Final = "units"


class Pulses:
    """`trigger/pulses/`: the box's pulse records, all int64."""

    GROUP: Final = "pulses"
    INDEX: Final = "index"
    T_US: Final = "t_us"
    HOST_TIME_NS: Final = "host_time_ns"


class Sync:
    """`sync/`, written on finalize: the report and each device's exact clock map."""

    REPORT: Final = "report_json"
    DEVICES: Final = "devices"
    DEVICE_REF: Final = "device_ref_us"
    RIG_REF: Final = "rig_ref_us"
    RATE: Final = "rate"
    FRAC: Final = "frac_us"
    DRIFT_PPM: Final = "drift_ppm"
    RESIDUAL_RMS: Final = "residual_rms_us"
    RESIDUAL_MAX: Final = "residual_max_us"
    MISSING_PULSES: Final = "missing_pulses"
    DROPPED_FRAMES: Final = "dropped_frames"


ROOT_ATTRS = (
    Root.SCHEMA,
    Root.SCHEMA_VERSION,
    Root.STATUS,
    Root.TAKE_ID,
    Root.CREATED_UTC,
    Root.RIGD_VERSION,
    Root.TIME_DOMAIN,
)
#: `events/<sensor>/<name>`: p is stored as uint8 1/0 (DSEC), not the in-memory int8 +1/-1.
EVENT_DTYPES: dict[str, str] = {
    Events.X: "uint16",
    Events.Y: "uint16",
    Events.P: "uint8",
    Events.T: "int64",
}
#: `events/<sensor>/trigger/<name>`
TRIGGER_DTYPES: dict[str, str] = {
    TriggerEdges.T: "int64",
    TriggerEdges.P: "uint8",
    TriggerEdges.CHANNEL: "uint8",
    TriggerEdges.T_DEVICE: "int64",
    TriggerEdges.HOST_TIME_NS: "int64",
}
#: The first columns of `evt_index`; the decoder state of the sensor's format follows.
#: `follows`: 1 when the row's bytes continue the previous row's in the sensor's stream (nothing
#: refused or lost between, the same shift), so the two decode as one piece.
EVT_INDEX_COLUMNS = ("byte_start", "byte_len", "events", "t_first", "t_last", "shift_us", "follows")
#: `frames/<camera>/<name>`, all int64, one entry per frame.
FRAME_SERIES = (
    Frames.T_EXPOSURE_START,
    Frames.T_EXPOSURE_START_DEVICE,
    Frames.EXPOSURE,
    Frames.FRAME_COUNTER,
    Frames.PULSE_INDEX,
    Frames.HOST_TIME_NS,
)
#: `trigger/pulses/<name>`, all int64.
PULSE_SERIES = (Pulses.INDEX, Pulses.T_US, Pulses.HOST_TIME_NS)


def event_group(sensor: str) -> str:
    """`events/<sensor>`."""
    return f"{EVENTS_GROUP}/{sensor}"


def frame_group(camera: str) -> str:
    """`frames/<camera>`."""
    return f"{FRAMES_GROUP}/{camera}"


def trigger_in_group(sensor: str) -> str:
    """`events/<sensor>/trigger`."""
    return f"{EVENTS_GROUP}/{sensor}/{Events.TRIGGER}"


#: `trigger/pulses`.
PULSES_PATH: Final = f"{TRIGGER_GROUP}/{Pulses.GROUP}"
#: `sync/report_json`.
SYNC_REPORT_PATH: Final = f"{SYNC_GROUP}/{Sync.REPORT}"
