"""The daemon's wire protocol: control requests/replies and telemetry, as pydantic models.

Control is ZeroMQ REQ/REP with one JSON object per message. Every request carries the
protocol version `v`; a daemon answers a version it does not speak with a structured
error instead of guessing. Replies always echo the request `id` (when one could be read)
so scripts can match them. Telemetry is a PUB socket: topic `status` carries a
`Telemetry` JSON document, topic `thumb.<device>` a JSON header and a JPEG.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from rigd.core.fault_codes import FaultCode
from rigd.core.kinds import DeviceKind, SensorKind
from rigd.core.schema import LossRecord

PROTOCOL_VERSION = 1
#: Largest control message the daemon reads; bigger ones are refused by ZeroMQ itself.
MAX_MESSAGE_BYTES = 64 * 1024

Command = Literal[
    "ping",
    "status",
    "capture",
    "stop",
    "devices",
    "config",
    "recover",
    "shutdown",
    "capture_part",
    "pulses",
    "take_read",
    "take_stat",
]
COMMANDS: tuple[str, ...] = Command.__args__  # type: ignore[attr-defined]

ErrorCode = Literal[
    "bad_json",  # not UTF-8 JSON, or not a JSON object
    "bad_request",  # valid JSON that does not match the request model; `field` names where
    "unknown_command",
    "unsupported_version",
    "busy",  # e.g. capture while a take is running
    "not_capturing",  # stop with no take running
    "config_error",
    "device_error",
    "take_error",
    "internal",  # a bug: the daemon logged a traceback and goes on serving
]

DaemonState = Literal["idle", "starting", "capturing", "stopping", "error"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class _StrictRequest(BaseModel):
    """Requests come from anyone who can reach the socket: no coercion (a string is not a bool
    or an int, a bool is not an int, a float is not an int), no unknown fields."""

    model_config = ConfigDict(extra="forbid", strict=True)


# -- requests --------------------------------------------------------------------------------


class Request(_StrictRequest):
    """Envelope of every control request."""

    v: int = Field(description="Protocol version the client speaks.")
    id: Annotated[str, Field(max_length=64)] | None = Field(None, description="Echoed in the reply.")
    cmd: str = Field(max_length=32)
    args: dict[str, Any] = Field(default_factory=dict)


class NoArgs(_StrictRequest):
    pass


class CaptureArgs(_StrictRequest):
    duration_s: float | None = Field(
        None, gt=0, le=7 * 86400, description="Seconds of trigger pulses; None: until `stop`."
    )
    label: Annotated[str, Field(pattern=r"^[A-Za-z0-9_.-]{1,64}$")] | None = Field(
        None, description="Goes into the take file name and attributes."
    )


_STEM = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$"


class CapturePartArgs(_StrictRequest):
    """The coordinator of a multi-host rig arms this host: its devices record into the part
    `<stem>.<host>.part.h5`, on the coordinator's pulses (docs/multi-host.md)."""

    stem: Annotated[str, Field(pattern=_STEM)] = Field(description="The joined take's name, without .h5.")
    duration_s: float | None = Field(None, gt=0, le=7 * 86400)
    label: Annotated[str, Field(pattern=r"^[A-Za-z0-9_.-]{1,64}$")] | None = None


class PulsesArgs(_StrictRequest):
    """A follower host asks the coordinator for the take's pulse records from `since` on."""

    stem: Annotated[str, Field(pattern=_STEM)]
    since: int = Field(ge=0, le=1 << 40)


class StopArgs(_StrictRequest):
    reason: Annotated[str, Field(max_length=200)] = "stop requested"


class ShutdownArgs(_StrictRequest):
    force: bool = Field(False, description="Stop a running take first (it is finalized, not lost).")


#: The most bytes one `take_read` returns (base64 in the reply: 4/3 of it).
TAKE_READ_MAX_BYTES = 4 << 20
_TAKE_FILE = r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,250}\.h5$"


class TakeStatArgs(_StrictRequest):
    file: Annotated[str, Field(max_length=255, pattern=_TAKE_FILE)] = Field(
        description="A take file's name in the daemon's take directory (no path)."
    )


class TakeReadArgs(TakeStatArgs):
    offset: int = Field(ge=0, description="First byte to read.")
    length: int = Field(gt=0, le=TAKE_READ_MAX_BYTES, description="Bytes to read (fewer at the end).")
    binary: bool = Field(
        False,
        description="The bytes as a second frame of the reply (`length` in the result says how many), "
        "not base64 in the JSON (`data_b64`).",
    )


#: A command's result may hold bytes under this key: they go out as the reply's second frame,
#: not in its JSON (take_read with binary=true).
PAYLOAD_KEY = "_payload"


ARGS_MODELS: dict[str, type[BaseModel]] = {
    "ping": NoArgs,
    "status": NoArgs,
    "capture": CaptureArgs,
    "stop": StopArgs,
    "devices": NoArgs,
    "config": NoArgs,
    "recover": NoArgs,
    "shutdown": ShutdownArgs,
    "capture_part": CapturePartArgs,
    "pulses": PulsesArgs,
    "take_read": TakeReadArgs,
    "take_stat": TakeStatArgs,
}


# -- replies ---------------------------------------------------------------------------------


class ErrorInfo(_Strict):
    code: ErrorCode
    message: str
    field: str | None = Field(None, description="Dotted path of the offending request field.")


class Reply(_Strict):
    v: int = PROTOCOL_VERSION
    id: str | None = None
    ok: bool
    result: dict[str, Any] | None = None
    error: ErrorInfo | None = None


# -- telemetry -------------------------------------------------------------------------------


class Fault(_Strict):
    """Something wrong right now (cleared when it stops being true)."""

    code: FaultCode
    device: str | None = None
    message: str
    since_utc: str


class DeviceTelemetry(_Strict):
    name: str
    kind: DeviceKind
    state: Literal["ok", "failed", "reconnecting", "idle"]
    total: int = Field(description="Frames, events or pulse records written this take.")
    rate_hz: float = Field(description="Frames, events or pulses per second over the last interval.")
    lost: int = Field(description="Items recorded as lost this take (all reasons).")
    reconnects: int = 0
    queued: int = Field(0, description="Items of this device waiting in the writer queue.")
    shed: int = Field(
        0, description="Events shed at the source this take while the host could not keep up (overload)."
    )
    last_data_age_s: float | None = Field(None, description="Seconds since the device last delivered.")
    interval_jitter_us: float | None = Field(
        None,
        description="Std of the device-clock intervals between consecutive trigger observations minus "
        "the trigger period, over the last interval: live health of the device's sync.",
    )


class TakeSummary(_Strict):
    path: str
    status: str
    verdict: Literal["complete", "degraded", "failed", "unfinished"] = Field(
        "complete", description="complete: nothing lost; degraded: sealed but lost data (rigd.take.verdict)."
    )
    verdict_reasons: list[str] = Field(default_factory=list, description="Why the verdict is not complete.")
    frames: dict[str, int]
    events: dict[str, int]
    bytes_written: int
    losses: list[LossRecord]
    warnings: list[str]
    residual_rms_us: dict[str, float]
    end_reason: str | None = None
    error: str | None = None


class HostTelemetry(_Strict):
    """Another host of a multi-host rig, as the coordinator last reached it."""

    name: str
    endpoint: str
    reachable: bool
    state: DaemonState | None = None
    take: str | None = None
    devices: list[str] = Field(default_factory=list)
    pulses: int = 0
    message: str | None = Field(None, description="Why it is unreachable, or its first fault.")


class Telemetry(_Strict):
    v: int = PROTOCOL_VERSION
    seq: int
    time_utc: str
    pid: int
    state: DaemonState
    take: str | None = None
    take_elapsed_s: float = 0.0
    pulses: int = 0
    queue_depth: int = 0
    queue_capacity: int = 0
    queue_bytes: int = 0
    queue_max_bytes: int = 0
    writer_busy: float = Field(
        0.0, description="Share of the last seconds the writer thread was busy (1 - headroom)."
    )
    event_capacity_hz: float | None = Field(
        None,
        description="Events per second this host's writer would hold at full load beside the current "
        "frames: the event sensors' rate over writer_busy (None while the writer is nearly idle).",
    )
    bytes_written: int = 0
    write_rate_bytes_s: float = 0.0
    last_flush_age_s: float | None = None
    flush_max_s: float = 0.0
    disk_free_bytes: int = 0
    disk_total_bytes: int = 0
    devices: list[DeviceTelemetry] = Field(default_factory=list)
    faults: list[Fault] = Field(default_factory=list)
    takes_completed: int = 0
    last_take: TakeSummary | None = None
    host: str | None = Field(None, description="This daemon's host on a multi-host rig.")
    hosts: list[HostTelemetry] = Field(
        default_factory=list, description="The coordinator's view of the other hosts (multi-host rigs)."
    )


class ThumbnailHeader(_Strict):
    """First frame of a `thumb.<device>` telemetry message; the second is the JPEG."""

    v: int = PROTOCOL_VERSION
    device: str
    kind: SensorKind
    width: int
    height: int
    time_utc: str
