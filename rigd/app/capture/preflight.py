"""Before a take starts: the rig's devices can do what the config asks of them, and the code
they will run is compiled.

Each device says which capabilities its settings need (`required_capabilities`); a device
that lacks one would fail mid-take or record data that cannot be synchronized, so the take
is refused up front, before any device is configured or a file is created, with one line
naming every such device.

Then every device compiles what acquiring runs (`Device.warm_up`: the EVT decoders, the
simulator's pixel kernels and encoder), while the trigger is still off. With a cold numba cache
(a fresh install, a new `NUMBA_CACHE_DIR`) that takes seconds; spent on the first packets of a
take instead, a simulated sensor fell seconds behind real time and recorded half the pulses.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Mapping
from typing import Any

from drivers.base import Capability, Device, explain_missing, missing_capabilities
from rigd.app.capture.ballast import check_ballast
from rigd.app.capture.channel import DeviceChannel, TriggerChannel
from rigd.app.config import RigConfig
from rigd.core.errors import ConfigError, DeviceError, RigdError

log = logging.getLogger(__name__)


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


def warm_up(devices: Iterable[tuple[str, Device]]) -> float:
    """Compile each device's acquisition kernels (`Device.warm_up`) before the trigger starts;
    the seconds it took, also logged per device. A device whose warm-up fails is named in one
    line (DeviceError): it would fail the same way on its first packet."""
    t0 = time.monotonic()
    spent = []
    for name, device in devices:
        t = time.monotonic()
        try:
            device.warm_up()
        except RigdError:
            raise
        except Exception as exc:
            raise DeviceError(
                f"{name}: compiling its acquisition code failed: {type(exc).__name__}: {exc}"
            ) from exc
        spent.append(f"{name} {time.monotonic() - t:.2f} s")
    total = time.monotonic() - t0
    log.info(
        "compiled the capture path (numba kernels) in %.2f s before the trigger: %s", total, ", ".join(spent)
    )
    return total


def prepare_rig(
    config: RigConfig,
    trigger: TriggerChannel,
    channels: Mapping[str, DeviceChannel[Any, Any]],
    n_pulses: int | None,
) -> None:
    """Everything between opening the rig's devices and creating the take: refuse a rig whose
    devices cannot do what the config asks (all named in one line) or whose disk ballast is too
    small for it, then configure every device and compile what acquiring runs."""
    wanted = trigger.device.required_capabilities(trigger.settings, n_pulses)
    check_rig(
        [
            ("trigger", config.trigger.spec, trigger.device, wanted),
            *((name, ch.spec, ch.device, ch.required_capabilities()) for name, ch in channels.items()),
        ]
    )
    check_ballast(
        config.writer,
        [channels[cam.name].ballast_bytes() for cam in config.cameras],
        len(config.event_sensors),
    )
    trigger.configure()
    for ch in channels.values():
        ch.configure()
    warm_up([("trigger", trigger.device), *((name, ch.device) for name, ch in channels.items())])
