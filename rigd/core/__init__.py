"""The small core of data types every package imports (and which imports none of them).

The names below load on first use (PEP 562): `from rigd.core.errors import RigdError` runs this
file first, and a command line that only wants the errors should not pay for numpy and pydantic.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rigd.core.devices import DeviceInfo, PulseBatch
    from rigd.core.errors import (
        BackendUnavailableError,
        ConfigError,
        DeviceError,
        DeviceTimeoutError,
        EventDataError,
        ProtocolError,
        RigdError,
        SyncError,
        TakeError,
        TakeFormatError,
    )
    from rigd.core.events import EventArray, TriggerEvents
    from rigd.core.frames import Frame
    from rigd.core.kinds import DeviceKind
    from rigd.core.settings import CameraSettings, EventSensorSettings, TriggerSettings, WriterConfig
    from rigd.core.timebase import ClockFit, ClockMap, fit_clock_map

#: Each exported name -> the module that holds it.
_WHERE = {
    "DeviceInfo": "rigd.core.devices",
    "DeviceKind": "rigd.core.kinds",
    "PulseBatch": "rigd.core.devices",
    "BackendUnavailableError": "rigd.core.errors",
    "ConfigError": "rigd.core.errors",
    "DeviceError": "rigd.core.errors",
    "DeviceTimeoutError": "rigd.core.errors",
    "EventDataError": "rigd.core.errors",
    "ProtocolError": "rigd.core.errors",
    "RigdError": "rigd.core.errors",
    "SyncError": "rigd.core.errors",
    "TakeError": "rigd.core.errors",
    "TakeFormatError": "rigd.core.errors",
    "EventArray": "rigd.core.events",
    "TriggerEvents": "rigd.core.events",
    "Frame": "rigd.core.frames",
    "CameraSettings": "rigd.core.settings",
    "EventSensorSettings": "rigd.core.settings",
    "TriggerSettings": "rigd.core.settings",
    "WriterConfig": "rigd.core.settings",
    "ClockFit": "rigd.core.timebase",
    "ClockMap": "rigd.core.timebase",
    "fit_clock_map": "rigd.core.timebase",
}


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module 'rigd.core' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)


__all__ = [
    "BackendUnavailableError",
    "CameraSettings",
    "DeviceInfo",
    "DeviceKind",
    "EventSensorSettings",
    "PulseBatch",
    "TriggerSettings",
    "WriterConfig",
    "ClockFit",
    "ClockMap",
    "ConfigError",
    "DeviceError",
    "DeviceTimeoutError",
    "EventArray",
    "EventDataError",
    "Frame",
    "ProtocolError",
    "RigdError",
    "SyncError",
    "TakeError",
    "TakeFormatError",
    "TriggerEvents",
    "fit_clock_map",
]
