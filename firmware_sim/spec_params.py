"""The query parameters of every `sim://` and `replay://` device spec, one bounded model per
device kind, checked before a device is made.

A spec's query is text a person wrote into a rig config: every parameter is refused unless it
is given once, parses as its type and lies in a range the physics of the device allows
(jitter far below any trigger period, clock offsets with headroom in int64 microseconds,
sensor sizes an EVT stream can address), so a typo or a hostile value is one line naming the
device, the parameter and the allowed range, never a traceback, a hang or a huge allocation.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, TypeVar

from annotated_types import Ge, Gt, Le, Lt
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, model_validator

from drivers.registry import DeviceSpec
from firmware_sim.cable import MAX_FOLLOWERS, MAX_SOCKET_PATH, MAX_STALL_S, MAX_WAIT_S
from rigd.core.errors import ConfigError

#: Device clocks count microseconds from 0; an offset within +-2^45 us (about 1.1 years of
#: uptime) leaves int64 headroom for every sum the sync engine makes.
MAX_OFFSET_US = 2**45
#: Crystal oscillators are good to about +-100 ppm; ten times that is a broken clock.
MAX_DRIFT_PPM = 1000.0
#: Trigger edge jitter: microseconds on real boxes; 1 ms is far beyond any of them, and still
#: far below the period of the fastest trigger rate a box runs at sim rates.
MAX_JITTER_US = 1000.0
#: EVT 2.0/2.1/3.0 address x and y in 11 bits.
MAX_SENSOR_SIDE = 2048
#: A simulated camera frame: at most 8192 on a side and 16 MP (48 MB as rgb8).
MAX_CAMERA_SIDE = 8192
MAX_CAMERA_PIXELS = 1 << 24
#: Fault windows and delays: within a week of a take's start.
MAX_FAULT_S = 7 * 86400.0
MAX_INDEX_LIST = 100_000

Offset = Annotated[float, Field(ge=-MAX_OFFSET_US, le=MAX_OFFSET_US)]
Drift = Annotated[float, Field(ge=-MAX_DRIFT_PPM, le=MAX_DRIFT_PPM)]
Seed = Annotated[int, Field(ge=0, le=2**32 - 1)]
Switch = Annotated[int, Field(ge=0, le=1)]
Clock = Literal["real", "virtual"]


def _index_list(value: str) -> str:
    """A comma-separated list of pulse or frame indices (`drop_frames=3,7`)."""
    parts = [v.strip() for v in value.split(",") if v.strip()]
    if len(parts) > MAX_INDEX_LIST:
        raise ValueError(f"more than {MAX_INDEX_LIST} indices")
    for part in parts:
        if not (part.isascii() and part.isdigit()) or int(part) > 2**31 - 1:
            raise ValueError(f"{part!r} is not an index in 0..{2**31 - 1}")
    return value


IndexList = Annotated[str, AfterValidator(_index_list)]


class SpecParams(BaseModel):
    """Base of the per-kind models: values arrive as the query's text; None: not given."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)


class CableSpecParams(SpecParams):
    """The simulated trigger cable's end (`firmware_sim.cable`, which checks how they combine)."""

    cable: Annotated[str, Field(min_length=1, max_length=MAX_SOCKET_PATH)] | None = None
    cable_role: Literal["lead", "follow"] | None = None
    cable_followers: Annotated[int, Field(ge=0, le=MAX_FOLLOWERS)] | None = None
    cable_wait_s: Annotated[float, Field(ge=0, le=MAX_WAIT_S)] | None = None
    cable_stall_s: Annotated[float, Field(ge=0, le=MAX_STALL_S)] | None = None


class _Placement(CableSpecParams):
    """What every simulated camera and event sensor takes (`firmware_sim.placement`)."""

    offset_us: Offset | None = None
    drift_ppm: Drift | None = None
    seed: Seed | None = None
    scene: Literal["sprites", "board"] | None = None
    unplug_at_s: Annotated[float, Field(ge=0, le=MAX_FAULT_S)] | None = None
    unplug_for_s: Annotated[float, Field(gt=0, le=MAX_FAULT_S)] | None = None
    clock_reset: Switch | None = None
    clock: Clock | None = None


class SimCameraParams(_Placement):
    width: Annotated[int, Field(ge=1, le=MAX_CAMERA_SIDE)] | None = None
    height: Annotated[int, Field(ge=1, le=MAX_CAMERA_SIDE)] | None = None
    format: Literal["mono8", "rgb8", "bayer_rg8"] | None = None
    buffer_frames: Annotated[int, Field(ge=1, le=1024)] | None = None
    drop_frames: IndexList | None = None
    busy_us: Annotated[int, Field(ge=0, le=1_000_000)] | None = None
    counter_reset: Switch | None = None
    open_delay_s: Annotated[float, Field(ge=0, le=600)] | None = None

    @model_validator(mode="after")
    def _frame_size(self) -> SimCameraParams:
        w, h = self.width or 1280, self.height or 720
        if w * h > MAX_CAMERA_PIXELS:
            raise ValueError(f"width x height = {w} x {h} is more than {MAX_CAMERA_PIXELS:,} pixels")
        return self


class SimEventSensorParams(_Placement):
    width: Annotated[int, Field(ge=1, le=MAX_SENSOR_SIDE)] | None = None
    height: Annotated[int, Field(ge=1, le=MAX_SENSOR_SIDE)] | None = None
    threshold: Annotated[float, Field(gt=0, le=1000)] | None = None
    buffer_packets: Annotated[int, Field(ge=1, le=65536)] | None = None
    pixel_model: Literal["ideal", "full"] | None = None
    sigma: Annotated[float, Field(ge=0, le=10)] | None = None
    threshold_on: Annotated[float, Field(gt=0, le=1000)] | None = None
    threshold_off: Annotated[float, Field(gt=0, le=1000)] | None = None
    refractory_us: Annotated[int, Field(ge=0, le=10_000_000)] | None = None
    leak_hz: Annotated[float, Field(ge=0, le=1e6)] | None = None
    shot_hz: Annotated[float, Field(ge=0, le=1e6)] | None = None
    hot_fraction: Annotated[float, Field(ge=0, le=1)] | None = None
    lowpass_hz: Annotated[float, Field(gt=0, le=1e6)] | None = None


class _Box(CableSpecParams):
    """A trigger box on a pty or fake HID device (sim and replay alike), and its host driver."""

    drop_pulses: IndexList | None = None
    garbage_every: Annotated[int, Field(ge=0, le=1_000_000)] | None = None
    boot_ms: Annotated[int, Field(ge=0, le=60_000)] | None = None
    seed: Seed | None = None
    transport: Literal["serial", "hid"] | None = None
    silent_after: Annotated[int, Field(ge=0, le=2**31 - 1)] | None = None
    garbage_after: Annotated[int, Field(ge=0, le=2**31 - 1)] | None = None
    reply_timeout_s: Annotated[float, Field(gt=0, le=60)] | None = None
    boot_timeout_s: Annotated[float, Field(gt=0, le=600)] | None = None
    clock: Clock | None = None


class SimTriggerParams(_Box):
    offset_us: Offset | None = None
    drift_ppm: Drift | None = None
    jitter_us: Annotated[float, Field(ge=0, le=MAX_JITTER_US)] | None = None


class ReplayTriggerParams(_Box):
    device: str | None = None


class _ReplayDevice(SpecParams):
    device: str | None = None
    clock: Clock | None = None
    unplug_at_s: Annotated[float, Field(ge=0, le=MAX_FAULT_S)] | None = None
    unplug_for_s: Annotated[float, Field(gt=0, le=MAX_FAULT_S)] | None = None
    clock_reset: Switch | None = None


class ReplayCameraParams(_ReplayDevice):
    buffer_frames: Annotated[int, Field(ge=1, le=1024)] | None = None
    drop_frames: IndexList | None = None
    preload: Annotated[int, Field(ge=0, le=4096)] | None = None


class ReplaySensorParams(_ReplayDevice):
    buffer_packets: Annotated[int, Field(ge=1, le=65536)] | None = None


P = TypeVar("P", bound=SpecParams)


def allowed_range(model: type[SpecParams], name: str) -> str | None:
    """The bounds of a numeric parameter as text (`0..4294967295`, `> 0 and <= 60`)."""
    field = model.model_fields.get(name)
    if field is None:
        return None
    lo = hi = None
    for meta in _metadata(field.annotation, field.metadata):
        if isinstance(meta, Ge):
            lo = f"{meta.ge:g}" if isinstance(meta.ge, float) else str(meta.ge)
        elif isinstance(meta, Gt):
            lo = f"> {meta.gt:g}"
        elif isinstance(meta, Le):
            hi = f"{meta.le:g}" if isinstance(meta.le, float) else str(meta.le)
        elif isinstance(meta, Lt):
            hi = f"< {meta.lt:g}"
    if lo is None or hi is None:
        return None
    return f"{lo} and <= {hi}" if lo.startswith(">") else f"{lo}..{hi}"


def _metadata(annotation: Any, own: list[Any]) -> list[Any]:
    """Constraints of a field, also those inside `Annotated[...] | None`."""
    found = list(own)
    for arg in getattr(annotation, "__args__", ()):
        found += list(getattr(arg, "__metadata__", ()))
        for meta in getattr(arg, "__metadata__", ()):
            found += list(getattr(meta, "metadata", ()))
    return found


def check_params(spec: DeviceSpec, model: type[P], device: str) -> P:
    """The spec's parameters as `model`, or a ConfigError naming the device, the parameter and
    what it allows. Unknown and repeated parameters are refused too."""
    where = f"device spec {spec.raw!r} ({device})"
    if spec.repeated:
        raise ConfigError(f"{where}: parameter(s) given more than once: {', '.join(spec.repeated)}")
    spec.check_params(set(model.model_fields))
    try:
        return model.model_validate(spec.params)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = err["loc"]
        if not loc:
            raise ConfigError(f"{where}: {str(err['msg']).removeprefix('Value error, ')}") from None
        name = str(loc[0])
        value = spec.params.get(name, "")
        bounds = allowed_range(model, name)
        kind = err["type"]
        allowed = f" (allowed: {bounds})" if bounds else ""
        if kind == "finite_number":
            why = f"is not a finite number{allowed}"
        elif kind.startswith(("greater_than", "less_than")):
            why = f"out of range{allowed}"
        else:
            why = f"is refused: {str(err['msg']).removeprefix('Value error, ')}{allowed}"
        raise ConfigError(f"{where}: {name}={value!r} {why}") from None


__all__ = [
    "CableSpecParams",
    "ReplayCameraParams",
    "ReplaySensorParams",
    "ReplayTriggerParams",
    "SimCameraParams",
    "SimEventSensorParams",
    "SimTriggerParams",
    "allowed_range",
    "check_params",
]
