"""The small core of data types every package imports (and which imports none of them)."""

from rigd.core.devices import DeviceInfo, DeviceKind, PulseBatch
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
from rigd.core.settings import CameraSettings, EventSensorSettings, TriggerSettings, WriterConfig
from rigd.core.timebase import ClockFit, ClockMap, fit_clock_map

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
