"""What discovery reports: the USB IDs rigd knows, a found device (with the spec that opens it), and
the per-source reports (a source that cannot run here says why instead of raising).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

DeviceRole = Literal["trigger", "rgb_camera", "event_sensor", "unknown"]


class SourceUnavailable(Exception):  # noqa: N818 - a condition, not a failure of the program
    """A discovery source cannot run on this machine; the message says why and what to install."""


@dataclass(frozen=True, slots=True)
class KnownUsb:
    """A USB vendor/product we recognise; `product_id=None` matches the whole vendor."""

    vendor_id: int
    product_id: int | None
    role: DeviceRole
    label: str


#: USB IDs rigd recognises. Generic USB-serial bridges count as trigger candidates: campy /
#: dattalab-style trigger boxes are Arduinos and Teensys behind exactly these.
KNOWN_USB: tuple[KnownUsb, ...] = (
    # Prophesee EVKs: Cypress FX3-based (EVK1..EVK4 generation) and Prophesee's own VID.
    KnownUsb(0x04B4, 0x00F3, "event_sensor", "Prophesee EVK (Cypress FX3)"),
    KnownUsb(0x04B4, 0x00F4, "event_sensor", "Prophesee EVK (Cypress FX3)"),
    KnownUsb(0x04B4, 0x00F5, "event_sensor", "Prophesee EVK (Cypress FX3)"),
    KnownUsb(0x31F7, None, "event_sensor", "Prophesee camera"),
    # Trigger boxes: Teensy (PJRC), Arduino, RP2040, common USB-UART bridges, pid.codes.
    KnownUsb(0x16C0, 0x0483, "trigger", "Teensy (USB serial)"),
    KnownUsb(0x16C0, 0x0486, "trigger", "Teensy (raw HID)"),
    KnownUsb(0x16C0, 0x0487, "trigger", "Teensy (dual serial)"),
    KnownUsb(0x2341, None, "trigger", "Arduino"),
    KnownUsb(0x2A03, None, "trigger", "Arduino (arduino.org)"),
    KnownUsb(0x1B4F, None, "trigger", "SparkFun (Arduino-compatible)"),
    KnownUsb(0x239A, None, "trigger", "Adafruit (Arduino-compatible)"),
    KnownUsb(0x2E8A, 0x000A, "trigger", "Raspberry Pi Pico (USB serial)"),
    KnownUsb(0x0403, 0x6001, "trigger", "FTDI FT232R serial bridge"),
    KnownUsb(0x0403, 0x6014, "trigger", "FTDI FT232H serial bridge"),
    KnownUsb(0x0403, 0x6015, "trigger", "FTDI FT231X serial bridge"),
    KnownUsb(0x1A86, 0x7523, "trigger", "CH340 serial bridge"),
    KnownUsb(0x10C4, 0xEA60, "trigger", "CP210x serial bridge"),
    KnownUsb(0x1209, 0x0001, "trigger", "pid.codes test device (rigd sim / DIY box)"),
    # USB3 Vision camera vendors (the class check below catches the others).
    KnownUsb(0x1E10, None, "rgb_camera", "Teledyne FLIR / Point Grey camera"),
    KnownUsb(0x2676, None, "rgb_camera", "Basler camera"),
    KnownUsb(0x1409, None, "rgb_camera", "IDS camera"),
    KnownUsb(0x1AB2, None, "rgb_camera", "Allied Vision camera"),
    KnownUsb(0x2BDF, None, "rgb_camera", "Hikrobot camera"),
    KnownUsb(0x2BA2, None, "rgb_camera", "Daheng camera"),
)


#: USB3 Vision control interface: class Miscellaneous (0xEF), subclass 0x05.
U3V_CLASS, U3V_SUBCLASS = 0xEF, 0x05


UVC_CLASS = 0x0E


HID_CLASS = 0x03


#: libusb / pyusb speed codes -> (label, Mbit/s).
USB_SPEEDS: dict[int, tuple[str, int]] = {
    1: ("low", 1),
    2: ("full", 12),
    3: ("high", 480),
    4: ("super", 5000),
    5: ("super+", 10000),
}


def usb_speed_label(mbps: int | None) -> str | None:
    """'USB 2 (480 Mbit/s)' style label from a link speed in Mbit/s."""
    if mbps is None:
        return None
    gen = "USB 3" if mbps >= 5000 else "USB 2" if mbps >= 480 else "USB 1"
    return f"{gen} ({mbps} Mbit/s)"


def lookup_usb(vid: int | None, pid: int | None) -> KnownUsb | None:
    """The table entry for a VID/PID; exact product matches win over vendor-wide ones."""
    if vid is None:
        return None
    vendor_wide: KnownUsb | None = None
    for k in KNOWN_USB:
        if k.vendor_id != vid:
            continue
        if k.product_id == pid:
            return k
        if k.product_id is None:
            vendor_wide = k
    return vendor_wide


@dataclass(slots=True)
class FoundDevice:
    """One thing found by one source, with the spec rigd would open it with (if any)."""

    source: str
    name: str
    role: DeviceRole = "unknown"
    spec: str | None = None
    path: str | None = None
    vendor_id: int | None = None
    product_id: int | None = None
    serial: str | None = None
    usb_speed_mbps: int | None = None
    details: dict[str, str] = field(default_factory=dict)

    @property
    def usb_id(self) -> str | None:
        if self.vendor_id is None or self.product_id is None:
            return None
        return f"{self.vendor_id:04x}:{self.product_id:04x}"

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["usb_id"] = self.usb_id
        d["usb_speed"] = usb_speed_label(self.usb_speed_mbps)
        return d


@dataclass(slots=True)
class SourceReport:
    source: str
    available: bool
    devices: list[FoundDevice] = field(default_factory=list)
    reason: str = ""


@dataclass(slots=True)
class Discovery:
    sources: list[SourceReport]

    @property
    def devices(self) -> list[FoundDevice]:
        return [d for s in self.sources for d in s.devices]

    @property
    def nothing_attached(self) -> bool:
        return not self.devices

    def by_role(self, role: DeviceRole) -> list[FoundDevice]:
        return [d for d in self.devices if d.role == role]

    def to_dict(self) -> dict[str, Any]:
        return {
            "nothing_attached": self.nothing_attached,
            "sources": [
                {
                    "source": s.source,
                    "available": s.available,
                    "reason": s.reason,
                    "devices": [d.to_dict() for d in s.devices],
                }
                for s in self.sources
            ],
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Discovery:
        """Inverse of `to_dict` (what a daemon's `devices` request returns)."""
        fields = set(FoundDevice.__dataclass_fields__)
        return cls(
            [
                SourceReport(
                    s["source"],
                    bool(s["available"]),
                    [FoundDevice(**{k: v for k, v in d.items() if k in fields}) for d in s["devices"]],
                    s.get("reason", ""),
                )
                for s in data["sources"]
            ]
        )
