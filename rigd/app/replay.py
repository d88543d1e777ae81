"""A rig config that replays a recorded take (`rigd capture --replay TAKE.h5`)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from rigd.app.config import RigConfig
from rigd.core.errors import ConfigError, RigdError
from rigd.take import Take


def _spec(take: Path, device: str, clock: str, extra: dict[str, str]) -> str:
    params = {"device": device, **extra}
    if clock == "virtual":
        params["clock"] = "virtual"
    return f"replay://{take}?" + "&".join(f"{k}={v}" for k, v in params.items())


def replay_config(
    take_path: Path,
    *,
    clock: Literal["real", "virtual"] = "real",
    faults: dict[str, dict[str, str]] | None = None,
) -> tuple[RigConfig, float]:
    """The take's own rig config with every device replaced by its replay, and the recorded
    duration (pulses / rate). `faults` adds spec parameters per device name (`trigger` for the
    box), e.g. {"cam1": {"drop_frames": "3"}}."""
    path = take_path.resolve()
    if not path.is_file():
        raise ConfigError(f"cannot replay {take_path}: no such file")
    try:
        with Take(path) as take:
            recorded = take.config
            report = take.sync_report
            n_pulses = int(take.pulses().index.size)
            cameras, sensors = set(take.cameras), set(take.event_sensors)
    except RigdError as exc:
        raise ConfigError(f"cannot replay {take_path}: {exc}") from None
    if report is None:
        raise ConfigError(
            f"cannot replay {take_path}: the take was never finalized; run `rigd recover` first"
        )
    if "trigger" not in recorded or n_pulses == 0:
        source = recorded.get("converted_from")
        made = f"made by `rigd convert` from {source}" if source else "recorded without a trigger"
        raise ConfigError(
            f"cannot replay {take_path}: it has no trigger box and no trigger pulses ({made}); "
            "a replay plays a take recorded by `rigd capture`"
        )
    try:
        config = RigConfig.from_data(recorded, source=f"recorded in {take_path}")
    except ConfigError as exc:
        raise ConfigError(f"cannot replay {take_path}: {exc}") from None
    faults = faults or {}
    unknown = sorted(set(faults) - cameras - sensors - {"trigger"})
    if unknown:
        raise ConfigError(f"cannot replay {take_path}: no device {unknown} in the take")
    config.trigger.spec = _spec(path, "trigger", clock, faults.get("trigger", {}))
    config.cameras = [c for c in config.cameras if c.name in cameras]
    config.event_sensors = [s for s in config.event_sensors if s.name in sensors]
    for cam in config.cameras:
        cam.spec = _spec(path, cam.name, clock, faults.get(cam.name, {}))
    for sensor in config.event_sensors:
        sensor.spec = _spec(path, sensor.name, clock, faults.get(sensor.name, {}))
    return config, n_pulses / config.trigger.settings.rate_hz
