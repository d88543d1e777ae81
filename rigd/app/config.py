"""Rig configuration: which devices, by which spec, with which settings.

Loaded from TOML, JSON or YAML; every error names the file and the field.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, Field, ValidationError, model_validator

from rigd.core.errors import ConfigError
from rigd.core.kinds import DeviceKind
from rigd.core.settings import STRICT, CameraSettings, EventSensorSettings, TriggerSettings, WriterConfig

_NAME = r"^[A-Za-z][A-Za-z0-9_-]{0,31}$"


class CameraConfig(BaseModel):
    model_config = STRICT

    name: str = Field(pattern=_NAME, description="Name in the take (`frames/<name>`).")
    spec: str = Field(description="Backend spec, e.g. `sim://default/cam0` or `genicam://SERIAL`.")
    settings: CameraSettings = Field(default_factory=CameraSettings)
    host: str | None = Field(
        None, pattern=_NAME, description="Host (a key of `hosts`) whose daemon runs it; None: one host."
    )


class EventSensorConfig(BaseModel):
    model_config = STRICT

    name: str = Field(pattern=_NAME, description="Name in the take (`events/<name>`).")
    spec: str = Field(description="Backend spec, e.g. `sim://default/ev0` or `file://rec.raw`.")
    settings: EventSensorSettings = Field(default_factory=EventSensorSettings)
    host: str | None = Field(
        None, pattern=_NAME, description="Host (a key of `hosts`) whose daemon runs it; None: one host."
    )
    read_interval_ms: float = Field(
        5.0,
        ge=0.0,
        le=100.0,
        description="The capture reads the sensor at most once per this many ms; what arrived in "
        "between comes as one packet. Fewer, larger packets cost the host less per event "
        "(bench.capacity --parts device); 0 reads each buffer as it comes.",
    )


class TriggerConfig(BaseModel):
    model_config = STRICT

    spec: str = Field(description="Trigger box port or spec, e.g. `/dev/ttyACM0`.")
    settings: TriggerSettings = Field(default_factory=TriggerSettings)
    host: str | None = Field(
        None, pattern=_NAME, description="Host owning the trigger box: it coordinates a multi-host rig."
    )


def runtime_dir() -> Path:
    """Where the daemon's sockets live: $RIGD_RUNTIME_DIR, systemd's $RUNTIME_DIRECTORY,
    $XDG_RUNTIME_DIR/rigd, /run/rigd when the system service runs, else /tmp/rigd-<uid>
    (created owner-only)."""
    for var, sub in (("RIGD_RUNTIME_DIR", ""), ("RUNTIME_DIRECTORY", ""), ("XDG_RUNTIME_DIR", "rigd")):
        base = os.environ.get(var)
        if base:
            return Path(base.split(":")[0]) / sub if sub else Path(base.split(":")[0])
    if Path("/run/rigd/control.sock").exists():  # the systemd unit's RuntimeDirectory
        return Path("/run/rigd")
    return Path(tempfile.gettempdir()) / f"rigd-{os.getuid()}"


def default_control_endpoint() -> str:
    return f"ipc://{runtime_dir() / 'control.sock'}"


def default_telemetry_endpoint() -> str:
    return f"ipc://{runtime_dir() / 'telemetry.sock'}"


_LOOPBACK = ("127.0.0.1", "localhost", "[::1]", "::1")


class CurveConfig(BaseModel):
    """CurveZMQ keys (`rigd keys` writes them): the only way to listen beyond loopback."""

    model_config = STRICT

    server_secret_key: Path = Field(strict=False, description="Daemon's secret key file (zmq.auth format).")
    authorized_keys_dir: Path = Field(
        strict=False, description="Directory of the client public keys allowed in."
    )


class ServiceConfig(BaseModel):
    """How `rigd serve` listens and reports; defaults are local and owner-only."""

    model_config = STRICT

    control: str | None = Field(None, description="ZeroMQ control endpoint; None: IPC in the runtime dir.")
    telemetry: str | None = Field(None, description="ZeroMQ endpoint of the telemetry PUB socket.")
    take_dir: Path = Field(
        Path("takes"), strict=False, description="Where takes are written (and recovered on start)."
    )
    telemetry_interval_s: float = Field(1.0, ge=0.05, le=60.0)
    thumbnail_interval_s: float = Field(2.0, ge=0.0, le=3600.0, description="0 turns thumbnails off.")
    thumbnail_width: int = Field(320, ge=16, le=4096)
    metrics_host: str = Field("127.0.0.1", description="Prometheus exporter address.")
    metrics_port: int | None = Field(9464, ge=0, le=65535, description="None turns the exporter off.")
    metrics_token_file: Path | None = Field(
        None,
        description="File (mode 0600) holding a bearer token every scrape must send; required "
        "when metrics_host is not loopback.",
    )
    reconnect_interval_s: float = Field(1.0, ge=0.0, le=60.0, description="0: a lost device is written off.")
    recover_on_start: bool = Field(True, description="Seal takes a crash left unfinished before serving.")
    curve: CurveConfig | None = None
    host: str | None = Field(
        None, pattern=_NAME, description="This daemon's host (a key of `hosts`) on a multi-host rig."
    )

    @model_validator(mode="after")
    def _secure_endpoints(self) -> ServiceConfig:
        for name in ("control", "telemetry"):
            ep = getattr(self, name)
            if ep is None:
                continue
            scheme, sep, rest = ep.partition("://")
            if not sep or scheme not in ("ipc", "tcp"):
                raise ValueError(f"service.{name}: {ep!r} is not an ipc:// or tcp:// endpoint")
            if scheme == "tcp":
                host = rest.rsplit(":", 1)[0]
                if host not in _LOOPBACK and self.curve is None:
                    raise ValueError(
                        f"service.{name}: {ep} listens beyond loopback; that needs CurveZMQ keys "
                        "(service.curve) or a loopback address"
                    )
        return self

    @property
    def control_endpoint(self) -> str:
        return self.control or default_control_endpoint()

    @property
    def telemetry_endpoint(self) -> str:
        return self.telemetry or default_telemetry_endpoint()


class HostConfig(BaseModel):
    """One capture host of a multi-host rig (docs/multi-host.md): how the others reach its daemon."""

    model_config = STRICT

    control: str = Field(description="The host's daemon control endpoint, e.g. `tcp://10.0.0.2:5601`.")
    server_public_key: Path | None = Field(
        None, strict=False, description="That daemon's public key file (CurveZMQ); needed beyond loopback."
    )
    client_secret_key: Path | None = Field(
        None, strict=False, description="This side's secret key file to present to it (CurveZMQ)."
    )


class RigConfig(BaseModel):
    model_config = STRICT

    name: str = "rig"
    trigger: TriggerConfig
    cameras: list[CameraConfig] = Field(default_factory=list)
    event_sensors: list[EventSensorConfig] = Field(default_factory=list)
    writer: WriterConfig = Field(default_factory=WriterConfig)
    service: ServiceConfig = Field(default_factory=ServiceConfig)
    hosts: dict[str, HostConfig] = Field(
        default_factory=dict, description="Capture hosts of a multi-host rig, by name; empty: one host."
    )

    @model_validator(mode="after")
    def _hosts_known(self) -> RigConfig:
        placed = [("trigger.host", self.trigger.host)]
        placed += [(f"cameras.{i}.host", c.host) for i, c in enumerate(self.cameras)]
        placed += [(f"event_sensors.{i}.host", s.host) for i, s in enumerate(self.event_sensors)]
        for key in self.hosts:
            if not re.fullmatch(_NAME, key):
                raise ValueError(f"hosts.{key}: a host name is a letter, then letters, digits, _ or -")
        for where, host in placed:
            if self.hosts and host is None:
                raise ValueError(f"{where}: a multi-host rig (hosts) places every device on a host")
            if host is not None and host not in self.hosts:
                known = ", ".join(sorted(self.hosts)) or "none"
                raise ValueError(f"{where}: unknown host {host!r} (hosts: {known})")
        return self

    @property
    def coordinator(self) -> str | None:
        """The host that owns the trigger box (None on a one-host rig)."""
        return self.trigger.host

    def host_names(self) -> list[str]:
        """Hosts with devices, the coordinator first."""
        used = [self.trigger.host, *(c.host for c in self.cameras), *(s.host for s in self.event_sensors)]
        return list(dict.fromkeys(h for h in used if h is not None))

    def for_host(self, host: str) -> RigConfig:
        """The rig as `host`'s daemon runs it: only its cameras and event sensors (the trigger's
        settings stay: every host's take fits its devices to the same pulses)."""
        data = self.model_dump(mode="json")
        data["cameras"] = [c for c in data["cameras"] if c["host"] == host]
        data["event_sensors"] = [s for s in data["event_sensors"] if s["host"] == host]
        return RigConfig.from_data(data, source=f"rig {self.name!r} on host {host}")

    def devices_on(self, host: str) -> list[str]:
        """Names of the cameras and event sensors that `host` runs."""
        return [c.name for c in self.cameras if c.host == host] + [
            s.name for s in self.event_sensors if s.host == host
        ]

    @model_validator(mode="after")
    def _unique_names(self) -> RigConfig:
        names = [c.name for c in self.cameras] + [s.name for s in self.event_sensors]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"device names must be unique; repeated: {', '.join(dupes)}")
        if not names:
            raise ValueError("a rig needs at least one camera or event sensor")
        modes = {s.name: s.settings.sync_mode for s in self.event_sensors}
        for sen in self.event_sensors:
            st = sen.settings
            if st.sync_mode == "slave":
                if st.sync_master is None:
                    raise ValueError(f"event sensor {sen.name}: sync_mode slave needs sync_master")
                if modes.get(st.sync_master) != "master":
                    raise ValueError(
                        f"event sensor {sen.name}: sync_master {st.sync_master!r} is not an event "
                        "sensor of this rig in sync_mode master"
                    )
            elif st.sync_master is not None:
                raise ValueError(f"event sensor {sen.name}: sync_master is only for sync_mode slave")
        tr = self.trigger.settings
        period_us = 1e6 / tr.rate_hz
        if tr.pulse_width_us >= period_us:
            raise ValueError(
                f"trigger.settings.pulse_width_us: {tr.pulse_width_us} us does not fit the "
                f"{period_us:.0f} us period of rate_hz {tr.rate_hz:g}"
            )
        for i, cam in enumerate(self.cameras):
            cs = cam.settings
            if cs.trigger_mode == "hardware" and cs.exposure_us >= period_us:
                raise ValueError(
                    f"cameras.{i}.settings.exposure_us: {cs.exposure_us} us exposure is longer than the "
                    f"{period_us:.0f} us trigger period (trigger.settings.rate_hz {tr.rate_hz:g}): "
                    "impossible frame rate"
                )
        return self

    def on_virtual_time(self) -> bool:
        """Whether the rig's simulated devices run on virtual time (`clock=virtual` in a spec):
        its pulses then come at the simulation's pace, and wall-clock deadlines do not apply."""
        from drivers.registry import DeviceSpec

        specs = [self.trigger.spec, *(c.spec for c in self.cameras), *(s.spec for s in self.event_sensors)]
        return any(DeviceSpec.parse(spec).params.get("clock") == "virtual" for spec in specs)

    def check_devices(self) -> None:
        """Check every device spec without opening anything (see `drivers.registry.check_spec`);
        the error names the config field."""
        from drivers.registry import check_spec

        fields: list[tuple[str, DeviceKind, str]] = [("trigger.spec", "trigger", self.trigger.spec)]
        fields += [(f"cameras.{i}.spec", "rgb_camera", c.spec) for i, c in enumerate(self.cameras)]
        fields += [
            (f"event_sensors.{i}.spec", "event_sensor", s.spec) for i, s in enumerate(self.event_sensors)
        ]
        for where, kind, spec in fields:
            try:
                check_spec(kind, spec)
            except ConfigError as exc:
                raise ConfigError(f"{where}: {exc}") from None

    @classmethod
    def load(cls, path: str | Path) -> RigConfig:
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8")
        except OSError as exc:
            raise ConfigError(f"cannot read rig config {p}: {exc.strerror}") from exc
        except UnicodeDecodeError as exc:
            bad = exc.object[exc.start]
            raise ConfigError(
                f"rig config {p} is not a text file: byte {exc.start} (0x{bad:02x}) is not UTF-8"
            ) from None
        suffix = p.suffix.lower()
        try:
            data: Any
            if suffix == ".toml":
                data = tomllib.loads(text)
            elif suffix == ".json":
                data = json.loads(text)
            elif suffix in (".yaml", ".yml"):
                import yaml

                data = yaml.safe_load(text)
            else:
                raise ConfigError(f"rig config {p}: unknown extension {suffix!r} (use .toml, .json or .yaml)")
        except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
            raise ConfigError(f"rig config {p} is not valid {suffix[1:].upper()}: {exc}") from exc
        except Exception as exc:
            if exc.__class__.__module__.startswith("yaml"):
                raise ConfigError(f"rig config {p} is not valid YAML: {exc}") from exc
            raise
        return cls.from_data(data, source=str(p))

    @classmethod
    def from_data(cls, data: Any, source: str = "<config>") -> RigConfig:
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            parts = []
            for err in exc.errors():
                where = ".".join(str(x) for x in err["loc"])
                msg = str(err["msg"]).removeprefix("Value error, ")
                given = err.get("input")
                if isinstance(given, bool | int | float | str) and err["type"] != "value_error":
                    msg += f" (given: {given!r})"  # strict: `true` or "30" is not a number here
                parts.append(f"{where}: {msg}" if where else msg)
            raise ConfigError(f"rig config {source}: " + "; ".join(parts)) from None


def default_sim_rig(
    world: str = "default",
    seed: int = 0,
    pixel_format: Literal["mono8", "rgb8", "bayer_rg8"] = "bayer_rg8",
    resolution: tuple[int, int] = (1280, 720),
    rate_hz: float = 30.0,
    clock: Literal["real", "virtual"] = "real",
) -> RigConfig:
    """The built-in simulated rig of the paper: 3 RGB cameras, 2 event sensors, one trigger.

    Clock offsets and drifts differ per device (within +-100 ppm) so the sync engine has
    real work to do; the trigger edges jitter by 2 us. `clock="virtual"` runs the world on
    virtual time: as fast as the CPU allows, the same data for the same seed.
    """
    tail = "&clock=virtual" if clock == "virtual" else ""
    clocks = {
        "cam0": (1_503_311, 80.0),
        "cam1": (73_005_123, -60.0),
        "cam2": (9_120_007, 35.0),
        "ev0": (412_775, -95.0),
        "ev1": (5_600_900, 100.0),
    }

    width, height = resolution

    def spec(name: str) -> str:
        off, ppm = clocks[name]
        return (
            f"sim://{world}/{name}?offset_us={off}&drift_ppm={ppm}&seed={seed}&width={width}&height={height}"
            + tail
        )

    return RigConfig(
        name="sim-rig",
        trigger=TriggerConfig(
            spec=f"sim://{world}/trigger?drift_ppm=12&jitter_us=2&seed={seed}{tail}",
            settings=TriggerSettings(rate_hz=rate_hz, pulse_width_us=min(1000, int(2e5 / rate_hz))),
        ),
        cameras=[
            CameraConfig(
                name=n,
                spec=spec(n),
                settings=CameraSettings(exposure_us=8000, pixel_format=pixel_format),
            )
            for n in ("cam0", "cam1", "cam2")
        ],
        event_sensors=[EventSensorConfig(name=n, spec=spec(n)) for n in ("ev0", "ev1")],
    )


#: Scenes the simulator draws (firmware_sim: the `scene` parameter of sim camera and sensor specs).
SIM_SCENES = ("sprites", "board")


def with_sim_scene(rig: RigConfig, scene: str) -> RigConfig:
    """The rig with every sim:// camera and event sensor watching `scene` (`board`: the moving
    calibration chessboard). The trigger takes no scene: a world has one scene, which its devices
    share. A rig without sim cameras or sensors is refused: a real device films what is there."""
    if scene not in SIM_SCENES:
        raise ConfigError(f"--scene {scene!r}: use {' or '.join(SIM_SCENES)}")

    def with_scene(spec: str) -> str:
        if not spec.startswith("sim://"):
            return spec
        base, _, query = spec.partition("?")
        params = [p for p in query.split("&") if p and not p.startswith("scene=")]
        return f"{base}?{'&'.join([*params, f'scene={scene}'])}"

    data = rig.model_dump(mode="json")
    devices = [*data["cameras"], *data["event_sensors"]]
    if not any(d["spec"].startswith("sim://") for d in devices):
        raise ConfigError(f"--scene applies to sim:// cameras and event sensors; rig {rig.name!r} has none")
    for dev in devices:
        dev["spec"] = with_scene(dev["spec"])
    return RigConfig.from_data(data, source=f"{rig.name} with scene={scene}")
