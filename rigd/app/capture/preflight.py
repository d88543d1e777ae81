"""Before a take starts: the rig's devices can do what the config asks of them.

Each device says which capabilities its settings need (`required_capabilities`); a device
that lacks one would fail mid-take or record data that cannot be synchronized, so the take
is refused up front, before any device is configured or a file is created, with one line
naming every such device.
"""

from __future__ import annotations

from collections.abc import Iterable

from drivers.base import Capability, Device, explain_missing, missing_capabilities
from rigd.core.errors import ConfigError


def check_rig(devices: Iterable[tuple[str, str, Device, frozenset[Capability]]]) -> None:
    """`devices`: (rig name, its spec in the config, the opened device, the capabilities its
    settings need). Raises ConfigError naming each device, what it lacks and why."""
    problems = []
    for name, spec, device, wanted in devices:
        missing = missing_capabilities(device, wanted)
        if missing:
            problems.append(f"{name} ({spec}) lacks {explain_missing(missing)}")
    if problems:
        raise ConfigError(
            "not starting a take: the rig config asks for what its devices cannot do: " + " | ".join(problems)
        )
