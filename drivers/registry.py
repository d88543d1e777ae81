"""Backend selection by URL-like device spec, the way pyserial's `serial_for_url` works.

A spec's scheme picks the backend: `sim://rig/rgb0?drift_ppm=20`, `serial:///dev/ttyACM0`,
a bare `/dev/ttyACM0` (serial), `file://take.raw`, ... Backends register under
(kind, scheme). Built-in ones are named by import path so that importing `drivers` never
imports an optional library; other packages (the simulator among them) register through
the `rigd.backends` entry-point group as `"<kind>:<scheme>" = "module:factory"`, so runtime
code reaches them without importing them.
"""

from __future__ import annotations

import importlib
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import metadata
from typing import Literal, TypeVar, cast, overload
from urllib.parse import parse_qsl, urlsplit

from drivers.base import Device, EventSensor, RgbCamera, Trigger
from rigd.core.errors import BackendUnavailableError, ConfigError
from rigd.core.kinds import DeviceKind

log = logging.getLogger(__name__)

Factory = Callable[["DeviceSpec"], Device]
ENTRY_POINT_GROUP = "rigd.backends"

_BUILTIN: dict[tuple[str, str], str] = {
    ("trigger", "serial"): "drivers.serial_trigger:open_serial_trigger",
    ("trigger", "hid"): "drivers.serial_trigger:open_hid_trigger",
    ("event_sensor", "file"): "drivers.file_event_sensor:open_file_event_sensor",
    ("event_sensor", "prophesee"): "drivers.prophesee:open_prophesee_sensor",
    ("rgb_camera", "genicam"): "drivers.genicam_camera:open_genicam_camera",
    ("rgb_camera", "v4l2"): "drivers.v4l2_camera:open_v4l2_camera",
    ("rgb_camera", "file"): "drivers.file_camera:open_file_camera",
}
_registered: dict[tuple[str, str], Factory | str] = {}


@dataclass(frozen=True, slots=True)
class DeviceSpec:
    """A parsed device spec. `params` holds the query string, values as strings; `repeated`
    the names the query gave more than once (`params` keeps the last; `check_params` refuses)."""

    raw: str
    scheme: str
    location: str
    path: str
    params: dict[str, str] = field(default_factory=dict)
    repeated: tuple[str, ...] = ()

    @classmethod
    def parse(cls, spec: str) -> DeviceSpec:
        spec = spec.strip()
        if not spec:
            raise ConfigError("empty device spec")
        if "://" not in spec:
            # Bare device node or COM port: a serial port, as pyserial treats it.
            return cls(spec, "serial", "", spec, {})
        parts = urlsplit(spec)
        if not parts.scheme:
            raise ConfigError(f"device spec {spec!r} has no scheme")
        try:
            pairs = parse_qsl(parts.query, keep_blank_values=True, strict_parsing=bool(parts.query))
        except ValueError as exc:
            raise ConfigError(f"device spec {spec!r}: bad query string: {exc}") from exc
        names = [name for name, _ in pairs]
        repeated = tuple(sorted({n for n in names if names.count(n) > 1}))
        return cls(spec, parts.scheme.lower(), parts.netloc, parts.path, dict(pairs), repeated)

    def param(self, name: str, default: str) -> str:
        return self.params.get(name, default)

    def float_param(self, name: str, default: float) -> float:
        value = self.params.get(name)
        if value is None:
            return default
        try:
            return float(value)
        except ValueError:
            raise ConfigError(f"device spec {self.raw!r}: {name}={value!r} is not a number") from None

    def int_param(self, name: str, default: int) -> int:
        value = self.params.get(name)
        if value is None:
            return default
        try:
            return int(value)
        except ValueError:
            raise ConfigError(f"device spec {self.raw!r}: {name}={value!r} is not an integer") from None

    def int_list_param(self, name: str) -> list[int]:
        value = self.params.get(name, "")
        try:
            return [int(v) for v in value.split(",") if v.strip()]
        except ValueError:
            raise ConfigError(
                f"device spec {self.raw!r}: {name}={value!r} is not a comma-separated integer list"
            ) from None

    def check_params(self, allowed: set[str]) -> None:
        """Reject unknown and repeated parameters: a typo must not be ignored silently, nor one
        of two values for the same name."""
        if self.repeated:
            raise ConfigError(
                f"device spec {self.raw!r}: parameter(s) given more than once: {', '.join(self.repeated)}"
            )
        unknown = sorted(set(self.params) - allowed)
        if unknown:
            raise ConfigError(
                f"device spec {self.raw!r}: unknown parameter(s) {', '.join(unknown)}; "
                f"allowed: {', '.join(sorted(allowed)) or 'none'}"
            )


def register_backend(kind: DeviceKind, scheme: str, factory: Factory | str) -> None:
    """Register a backend factory (or its "module:attr" path) for a kind and scheme."""
    _registered[(kind, scheme.lower())] = factory


def _entry_point_backends() -> dict[tuple[str, str], str]:
    found: dict[tuple[str, str], str] = {}
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        kind, _, scheme = ep.name.partition(":")
        if not scheme:
            log.warning("ignoring malformed backend entry point %r (want 'kind:scheme')", ep.name)
            continue
        found[(kind, scheme.lower())] = ep.value
    return found


def available_backends() -> dict[tuple[str, str], str]:
    """Every (kind, scheme) a spec may use, with where its factory lives."""
    table: dict[tuple[str, str], str] = dict(_BUILTIN)
    table.update(_entry_point_backends())
    for key, fac in _registered.items():
        table[key] = fac if isinstance(fac, str) else f"{fac.__module__}:{fac.__qualname__}"
    return table


def _load(target: str) -> Factory:
    module_name, _, attr = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise BackendUnavailableError(
            f"backend module {module_name!r} cannot be imported ({exc}); "
            "install the optional dependency it needs"
        ) from exc
    return cast(Factory, getattr(module, attr))


def _resolve(kind: DeviceKind, scheme: str) -> Factory:
    key = (kind, scheme)
    fac = _registered.get(key)
    if fac is None:
        fac = _entry_point_backends().get(key) or _BUILTIN.get(key)
    if fac is None:
        raise ConfigError(_no_backend(kind, scheme))
    return _load(fac) if isinstance(fac, str) else fac


def _no_backend(kind: DeviceKind, scheme: str) -> str:
    schemes = sorted({s for k, s in [*available_backends(), *_registered] if k == kind})
    return f"no {kind} backend for scheme {scheme!r} (known: {', '.join(schemes) or 'none'})"


def check_spec(kind: DeviceKind, spec: str) -> None:
    """Check a spec without opening anything: a backend exists for its scheme and, for a
    serial port given by path, the port exists. Raises ConfigError naming the problem."""
    parsed = DeviceSpec.parse(spec)
    key = (kind, parsed.scheme)
    if key not in _registered and key not in available_backends():
        raise ConfigError(f"unknown device URL {spec!r}: {_no_backend(kind, parsed.scheme)}")
    if parsed.scheme == "serial":
        port = parsed.path or parsed.location
        if port.startswith("/") and not os.path.exists(port):
            raise ConfigError(f"serial port {port} does not exist (is the trigger box plugged in?)")


D = TypeVar("D", bound=Device)


@overload
def open_device(kind: Literal["rgb_camera"], spec: str) -> RgbCamera: ...
@overload
def open_device(kind: Literal["event_sensor"], spec: str) -> EventSensor: ...
@overload
def open_device(kind: Literal["trigger"], spec: str) -> Trigger: ...
def open_device(kind: DeviceKind, spec: str) -> Device:
    """Open the device a spec names, checking the backend gave the kind asked for."""
    parsed = DeviceSpec.parse(spec)
    factory = _resolve(kind, parsed.scheme)
    log.debug("opening %s %r with %r", kind, spec, factory)
    device = factory(parsed)
    if device.kind != kind:
        device.close()
        raise ConfigError(f"spec {spec!r} opened a {device.kind}, expected a {kind}")
    return device
