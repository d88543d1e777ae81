"""Device interfaces (one per device kind), the lifecycle they share, and the backends that
implement them."""

from drivers.base import (
    AcquiringDevice,
    AcquisitionStats,
    Capability,
    Device,
    EventPacket,
    EventSensor,
    RgbCamera,
    Trigger,
    missing_capabilities,
)
from drivers.registry import open_device, register_backend
from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.settings import CameraSettings, EventSensorSettings, TriggerSettings

__all__ = [
    "AcquiringDevice",
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
    "missing_capabilities",
    "open_device",
    "register_backend",
]
