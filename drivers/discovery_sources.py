"""The discovery sources: one function per kind of attachment (serial ports, USB devices, HID
devices, V4L2 nodes, GenICam cameras), each returning `FoundDevice`s or raising SourceUnavailable
with what to install when it cannot run here (no libusb backend, no Aravis, no sysfs).
"""

from __future__ import annotations

import glob
import logging
import os
from pathlib import Path
from typing import Any

from drivers.found_devices import (
    U3V_CLASS,
    U3V_SUBCLASS,
    USB_SPEEDS,
    UVC_CLASS,
    DeviceRole,
    FoundDevice,
    SourceUnavailable,
    lookup_usb,
)

log = logging.getLogger(__name__)


def _sysfs_usb_speed(usb_device_path: str | None) -> int | None:
    """Link speed from a USB device's sysfs directory (`speed` holds Mbit/s: 12, 480, 5000, ...)."""
    if not usb_device_path:
        return None
    try:
        return int(float(Path(usb_device_path, "speed").read_text().strip()))
    except (OSError, ValueError):
        return None


def find_serial_ports() -> list[FoundDevice]:
    """pyserial's list_ports; built-in legacy UARTs without USB IDs are skipped (never a box here)."""
    try:
        from serial.tools import list_ports
    except ImportError as exc:
        raise SourceUnavailable(f"pyserial is not installed ({exc}); pip install pyserial") from exc
    out: list[FoundDevice] = []
    for p in list_ports.comports():
        if p.vid is None and (p.hwid in ("n/a", "") or os.path.basename(p.device).startswith("ttyS")):
            log.debug("skipping legacy serial port %s", p.device)
            continue
        known = lookup_usb(p.vid, p.pid)
        by_id = _serial_by_id(p.device)
        out.append(
            FoundDevice(
                source="serial",
                name=p.description if p.description and p.description != "n/a" else p.name,
                role=known.role if known and known.role == "trigger" else "unknown",
                spec=by_id or p.device,
                path=p.device,
                vendor_id=p.vid,
                product_id=p.pid,
                serial=p.serial_number,
                usb_speed_mbps=_sysfs_usb_speed(getattr(p, "usb_device_path", None)),
                details={
                    k: str(v)
                    for k, v in {
                        "manufacturer": p.manufacturer,
                        "product": p.product,
                        "known_as": known.label if known else None,
                        "location": p.location,
                    }.items()
                    if v
                },
            )
        )
    return out


def _serial_by_id(device: str) -> str | None:
    """The /dev/serial/by-id link of a port: stable across replugs, unlike ttyACM numbers."""
    try:
        real = os.path.realpath(device)
        for link in sorted(glob.glob("/dev/serial/by-id/*")):
            if os.path.realpath(link) == real:
                return link
    except OSError:
        return None
    return None


def find_usb_devices() -> list[FoundDevice]:
    """pyusb (libusb): every USB device we recognise by VID/PID or by USB3 Vision / UVC class."""
    try:
        import usb.core
    except ImportError as exc:
        raise SourceUnavailable(f"pyusb is not installed ({exc}); pip install pyusb") from exc
    try:
        devices = list(usb.core.find(find_all=True))
    except usb.core.NoBackendError as exc:
        raise SourceUnavailable(f"pyusb has no libusb backend ({exc}); apt-get install libusb-1.0-0") from exc
    except (usb.core.USBError, OSError) as exc:
        raise SourceUnavailable(f"libusb cannot list devices: {exc}") from exc
    out: list[FoundDevice] = []
    for dev in devices:
        vid, pid = int(dev.idVendor), int(dev.idProduct)
        classes = _interface_classes(dev)
        known = lookup_usb(vid, pid)
        role: DeviceRole = known.role if known else "unknown"
        label = known.label if known else ""
        if (U3V_CLASS, U3V_SUBCLASS) in classes:
            role, label = "rgb_camera", label or "USB3 Vision camera"
        elif not known and any(c == UVC_CLASS for c, _ in classes):
            role, label = "rgb_camera", "UVC camera (use its /dev/video node)"
        if role == "unknown" and not known:
            continue  # keyboards, hubs, ...: not ours
        speed = USB_SPEEDS.get(int(getattr(dev, "speed", 0) or 0))
        serial_nbr = _usb_string(dev, "serial_number")
        spec = None
        if role == "event_sensor":
            spec = f"prophesee://{serial_nbr or ''}"
        elif (U3V_CLASS, U3V_SUBCLASS) in classes:
            spec = f"genicam://{serial_nbr}" if serial_nbr else None
        out.append(
            FoundDevice(
                source="usb",
                name=_usb_string(dev, "product") or label or f"USB {vid:04x}:{pid:04x}",
                role=role,
                spec=spec,
                path=f"usb:{dev.bus}:{dev.address}",
                vendor_id=vid,
                product_id=pid,
                serial=serial_nbr,
                usb_speed_mbps=speed[1] if speed else None,
                details={k: v for k, v in {"known_as": label, "bus": str(dev.bus)}.items() if v},
            )
        )
    return out


def _interface_classes(dev: Any) -> set[tuple[int, int]]:
    found: set[tuple[int, int]] = set()
    try:
        for cfg in dev:
            for intf in cfg:
                found.add((int(intf.bInterfaceClass), int(intf.bInterfaceSubClass)))
    except Exception as exc:  # noqa: BLE001 - a descriptor we cannot read is not fatal to discovery
        log.debug("cannot read interface descriptors of %s: %s", dev, exc)
    return found


def _usb_string(dev: Any, attr: str) -> str | None:
    """String descriptors need the device opened: without permission they are simply absent."""
    try:
        value = getattr(dev, attr)
    except Exception as exc:  # noqa: BLE001 - usb.core raises ValueError/USBError/NotImplementedError
        log.debug("cannot read %s of %s: %s", attr, dev, exc)
        return None
    return str(value) if value else None


def find_hid_devices() -> list[FoundDevice]:
    """hidapi: vendor-defined HID interfaces (usage page >= 0xFF00) and known trigger IDs only."""
    try:
        import hid
    except ImportError as exc:
        raise SourceUnavailable(f"hidapi is not installed ({exc}); pip install hidapi") from exc
    try:
        entries = hid.enumerate()
    except OSError as exc:
        raise SourceUnavailable(f"hidapi cannot enumerate: {exc}") from exc
    out: list[FoundDevice] = []
    for e in entries:
        vid, pid = int(e.get("vendor_id", 0)), int(e.get("product_id", 0))
        known = lookup_usb(vid, pid)
        vendor_defined = int(e.get("usage_page", 0) or 0) >= 0xFF00
        if not (vendor_defined or (known and known.role == "trigger")):
            continue  # mice and keyboards
        serial_nbr = str(e.get("serial_number") or "") or None
        path = e.get("path", b"")
        out.append(
            FoundDevice(
                source="hid",
                name=str(e.get("product_string") or (known.label if known else f"HID {vid:04x}:{pid:04x}")),
                role="trigger" if known and known.role == "trigger" else "unknown",
                spec=f"hid://{vid:04x}:{pid:04x}" + (f"/{serial_nbr}" if serial_nbr else ""),
                path=path.decode(errors="replace") if isinstance(path, bytes) else str(path),
                vendor_id=vid,
                product_id=pid,
                serial=serial_nbr,
                details={
                    "usage_page": f"0x{int(e.get('usage_page', 0) or 0):04x}",
                    "interface": str(e.get("interface_number", "")),
                    **(
                        {"manufacturer": str(e["manufacturer_string"])}
                        if e.get("manufacturer_string")
                        else {}
                    ),
                },
            )
        )
    return out


def find_v4l2_nodes(
    dev_glob: str = "/dev/video*", sysfs: str = "/sys/class/video4linux"
) -> list[FoundDevice]:
    """/dev/video* with their sysfs names; metadata nodes (index != 0) are listed but not cameras."""
    if not os.path.isdir("/dev"):
        raise SourceUnavailable("no /dev: not a Linux machine (V4L2 is Linux-only)")
    out: list[FoundDevice] = []
    for node in sorted(glob.glob(dev_glob), key=_natural_key):
        base = os.path.basename(node)
        sys_dir = Path(sysfs, base)
        name = _read(sys_dir / "name") or base
        index = _read(sys_dir / "index")
        is_capture = index in (None, "0")
        usb_dir = _usb_parent(sys_dir / "device")
        vid = _read_hex(usb_dir / "idVendor") if usb_dir else None
        pid = _read_hex(usb_dir / "idProduct") if usb_dir else None
        out.append(
            FoundDevice(
                source="v4l2",
                name=name,
                role="rgb_camera" if is_capture else "unknown",
                spec=f"v4l2://{node}" if is_capture else None,
                path=node,
                vendor_id=vid,
                product_id=pid,
                serial=_read(usb_dir / "serial") if usb_dir else None,
                usb_speed_mbps=_sysfs_usb_speed(str(usb_dir)) if usb_dir else None,
                details={"index": index or "?", **({} if is_capture else {"note": "metadata node"})},
            )
        )
    return out


def _natural_key(s: str) -> tuple[str, int]:
    digits = "".join(ch for ch in s if ch.isdigit())
    return (s.rstrip("0123456789"), int(digits) if digits else -1)


def _read(p: Path) -> str | None:
    try:
        return p.read_text().strip()
    except OSError:
        return None


def _read_hex(p: Path) -> int | None:
    text = _read(p)
    try:
        return int(text, 16) if text else None
    except ValueError:
        return None


def _usb_parent(p: Path) -> Path | None:
    """The USB device directory above a sysfs interface (the one holding idVendor)."""
    try:
        cur = p.resolve()
    except OSError:
        return None
    for d in (cur, *cur.parents):
        if (d / "idVendor").exists():
            return d
        if d == Path("/sys"):
            break
    return None


def find_genicam_cameras() -> list[FoundDevice]:
    """Aravis device list (GigE Vision and USB3 Vision), when PyGObject + Aravis are installed."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise SourceUnavailable(
            f"Aravis is not available ({exc}); apt-get install gir1.2-aravis-0.8 and pip install PyGObject"
        ) from exc
    Aravis.update_device_list()
    out: list[FoundDevice] = []
    for i in range(Aravis.get_n_devices()):
        dev_id = Aravis.get_device_id(i)
        serial_nbr = Aravis.get_device_serial_nbr(i) or None
        protocol = Aravis.get_device_protocol(i) or ""
        out.append(
            FoundDevice(
                source="genicam",
                name=f"{Aravis.get_device_vendor(i) or ''} {Aravis.get_device_model(i) or ''}".strip()
                or dev_id,
                role="rgb_camera",
                spec=f"genicam://{serial_nbr or dev_id}",
                path=Aravis.get_device_address(i) or None,
                serial=serial_nbr,
                details={"device_id": dev_id, "protocol": protocol},
            )
        )
    return out
