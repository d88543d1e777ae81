"""Device interfaces (one per device kind) and the backends that implement them."""

from drivers.base import AcquisitionStats, Capability, Device, EventPacket, EventSensor, RgbCamera, Trigger
from drivers.registry import open_device, register_backend
from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.settings import CameraSettings, EventSensorSettings, TriggerSettings

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
