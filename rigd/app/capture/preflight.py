"""Before a take starts: the rig's devices can do what the config asks of them.

Each device says which capabilities its settings need (`required_capabilities`); a device
that lacks one would fail mid-take or record data that cannot be synchronized, so the take
is refused up front with one line naming every such device.
"""

from __future__ import annotations

from drivers.base import Capability, Device
from rigd.core.errors import ConfigError
from rigd.core.settings import CameraSettings, EventSensorSettings, TriggerSettings

Settings = CameraSettings | EventSensorSettings | TriggerSettings


def missing_capabilities(
    device: Device, settings: Settings, extra: frozenset[Capability] = frozenset()
) -> frozenset[Capability]:
    required = getattr(device, "required_capabilities", None)  # TEMP until the ABCs have it
    wanted = (frozenset() if required is None else required(settings)) | extra
    return frozenset(wanted - device.capabilities)


def check_rig(devices: dict[str, tuple[Device, Settings, frozenset[Capability]]]) -> None:
    """`devices`: name -> (opened device, its settings, what the take needs beyond them).
    Raises ConfigError naming each device and what it lacks."""
    problems = []
    for name, (device, settings, extra) in devices.items():
        missing = missing_capabilities(device, settings, extra)
        if missing:
            problems.append(f"{name} ({device.info.spec}) lacks {', '.join(sorted(missing))}")
    if problems:
        raise ConfigError(
            "not starting a take: the rig config asks for what its devices cannot do: " + "; ".join(problems)
        )
