"""Device interfaces (one per device kind) and the backends that implement them."""

from drivers.base import (
    AcquisitionStats,
    CameraSettings,
    Capability,
    Device,
    DeviceInfo,
    EventPacket,
    EventSensor,
    EventSensorSettings,
    PulseBatch,
    RgbCamera,
    Trigger,
    TriggerSettings,
)
from drivers.registry import open_device, register_backend

__all__ = [
    "AcquisitionStats",
    "CameraSettings",
    "Capability",
    "Device",
    "DeviceInfo",
    "EventPacket",
    "EventSensor",
    "EventSensorSettings",
    "PulseBatch",
    "RgbCamera",
    "Trigger",
    "TriggerSettings",
    "open_device",
    "register_backend",
]
