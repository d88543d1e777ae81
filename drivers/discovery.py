"""What is attached and usable: serial ports, USB devices, HID devices, V4L2 nodes, GenICam cameras.

Each source is a function returning `FoundDevice`s; a source that cannot run here (no
libusb backend, no Aravis, no sysfs) is reported as unavailable with the reason, never as
an exception, so `rigd devices` always prints what it could find. Sources are injectable
(`discover(sources=...)`) so tests run without hardware.

Also here, because they only need what discovery found: the rig-config skeleton
(`config_skeleton`) and the udev rules for stable symlinks (`udev_rules`).
"""

from __future__ import annotations

import glob
import json
import logging
import os
from collections.abc import Callable, Iterable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

log = logging.getLogger(__name__)

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


# ---------------------------------------------------------------------------- sources
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


Source = Callable[[], list[FoundDevice]]

DEFAULT_SOURCES: dict[str, Source] = {
    "serial": find_serial_ports,
    "usb": find_usb_devices,
    "hid": find_hid_devices,
    "v4l2": find_v4l2_nodes,
    "genicam": find_genicam_cameras,
}


def discover(sources: Mapping[str, Source] | None = None) -> Discovery:
    """Run every source; each fails soft into an unavailable report with the reason."""
    reports: list[SourceReport] = []
    for name, fn in (sources if sources is not None else DEFAULT_SOURCES).items():
        try:
            reports.append(SourceReport(name, True, fn()))
        except SourceUnavailable as exc:
            log.info("discovery source %s unavailable: %s", name, exc)
            reports.append(SourceReport(name, False, reason=str(exc)))
        except Exception as exc:
            log.warning("discovery source %s failed: %s", name, exc, exc_info=True)
            reports.append(SourceReport(name, False, reason=f"{type(exc).__name__}: {exc}"))
    return _merge(reports)


def _merge(reports: list[SourceReport]) -> Discovery:
    """A device seen by pyusb *and* as a serial port / HID device / V4L2 node / Aravis camera:
    keep the openable entry, give it the USB link speed, and drop the bare USB duplicate
    (Prophesee EVKs stay: only pyusb sees them)."""
    openable = {
        (d.vendor_id, d.product_id, d.serial)
        for r in reports
        if r.source != "usb"
        for d in r.devices
        if d.vendor_id is not None
    }
    speeds = {
        (d.vendor_id, d.product_id, d.serial): d.usb_speed_mbps
        for r in reports
        if r.source == "usb"
        for d in r.devices
    }
    for r in reports:
        if r.source == "usb":
            r.devices = [
                d
                for d in r.devices
                if d.role == "event_sensor" or (d.vendor_id, d.product_id, d.serial) not in openable
            ]
        else:
            for d in r.devices:
                if d.usb_speed_mbps is None:
                    d.usb_speed_mbps = speeds.get((d.vendor_id, d.product_id, d.serial))
    return Discovery(reports)


# ---------------------------------------------------------------------------- outputs
def config_skeleton(found: Discovery) -> tuple[dict[str, Any], list[str]]:
    """A rig config dict from what was found, and notes on what the operator must still edit."""
    notes: list[str] = []
    triggers = [d for d in found.by_role("trigger") if d.spec]
    if triggers:
        trigger_spec = triggers[0].spec
        if len(triggers) > 1:
            notes.append(
                f"{len(triggers)} trigger candidates; using {trigger_spec}, others: "
                + ", ".join(str(d.spec) for d in triggers[1:])
            )
    else:
        trigger_spec = "/dev/rigd-trigger"
        notes.append("no trigger box found: set trigger.spec (serial port or hid://VID:PID)")
    cameras = []
    for i, d in enumerate(d for d in found.by_role("rgb_camera") if d.spec):
        settings: dict[str, Any] = {"exposure_us": 8000}
        if d.source == "v4l2":
            settings["trigger_mode"] = "free_run"  # UVC cameras have no trigger input
            notes.append(f"cam{i} ({d.spec}) is free-running: its sync will be software-only")
        cameras.append({"name": f"cam{i}", "spec": d.spec, "settings": settings})
    sensors = [
        {"name": f"ev{i}", "spec": d.spec}
        for i, d in enumerate(d for d in found.by_role("event_sensor") if d.spec)
    ]
    if not cameras and not sensors:
        notes.append("no camera or event sensor found: add [[cameras]] / [[event_sensors]] before capturing")
    config: dict[str, Any] = {
        "name": "rig",
        "trigger": {"spec": trigger_spec, "settings": {"rate_hz": 30.0, "pulse_width_us": 1000}},
        "cameras": cameras,
        "event_sensors": sensors,
    }
    return config, notes


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    return json.dumps(str(v))  # TOML basic strings share JSON's escapes


def write_config_skeleton(found: Discovery, out: Path) -> list[str]:
    """Write the skeleton as TOML (.toml) or JSON (.json); returns the notes for the operator."""
    config, notes = config_skeleton(found)
    suffix = out.suffix.lower()
    if suffix == ".json":
        text = json.dumps(config, indent=2) + "\n"
    elif suffix == ".toml":
        lines = ["# Rig config skeleton written by `rigd devices --config` from the devices found."]
        lines += [f"# TODO: {n}" for n in notes]
        lines += [f"name = {_toml_value(config['name'])}", "", "[trigger]"]
        lines += [f"{k} = {_toml_value(v)}" for k, v in config["trigger"].items()]
        for section in ("cameras", "event_sensors"):
            for item in config[section]:
                lines += ["", f"[[{section}]]"] + [f"{k} = {_toml_value(v)}" for k, v in item.items()]
        text = "\n".join(lines) + "\n"
    else:
        raise ValueError(f"rig config skeleton {out}: use a .toml or .json file name")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")
    return notes


def udev_rules(devices: Iterable[FoundDevice]) -> str:
    """udev rules giving stable names: /dev/rigd-trigger[N] for boxes, /dev/rigd-camN for V4L2
    cameras, and group access (plugdev) for USB devices that libusb / hidraw open directly."""
    lines = [
        "# Generated by `rigd devices --udev`: stable symlinks for the devices found on this machine.",
        "# Install: sudo cp THIS_FILE /etc/udev/rules.d/99-rigd.rules && sudo udevadm control --reload"
        " && sudo udevadm trigger",
        "",
    ]
    n_trig = n_cam = 0
    seen: set[tuple[str, str, str | None]] = set()
    for d in devices:
        if d.vendor_id is None or d.product_id is None:
            continue
        key = (d.source, d.usb_id or "", d.serial)
        if key in seen:
            continue
        seen.add(key)
        match = f'ATTRS{{idVendor}}=="{d.vendor_id:04x}", ATTRS{{idProduct}}=="{d.product_id:04x}"'
        if d.serial:
            match += f', ATTRS{{serial}}=="{d.serial}"'
        what = f"# {d.name} ({d.usb_id}{', serial ' + d.serial if d.serial else ''})"
        if d.source == "serial" and d.role == "trigger":
            link = "rigd-trigger" if n_trig == 0 else f"rigd-trigger{n_trig}"
            n_trig += 1
            lines += [what, f'SUBSYSTEM=="tty", {match}, SYMLINK+="{link}", GROUP="dialout", MODE="0660"', ""]
        elif d.source == "hid" and d.role == "trigger":
            link = "rigd-trigger-hid" if n_trig == 0 else f"rigd-trigger{n_trig}-hid"
            n_trig += 1
            lines += [
                what,
                f'SUBSYSTEM=="hidraw", {match}, SYMLINK+="{link}", GROUP="plugdev", MODE="0660"',
                "",
            ]
        elif d.source == "v4l2" and d.role == "rgb_camera":
            lines += [
                what,
                f'SUBSYSTEM=="video4linux", {match}, ATTR{{index}}=="0", SYMLINK+="rigd-cam{n_cam}", '
                'GROUP="video", MODE="0660"',
                "",
            ]
            n_cam += 1
        elif d.source == "usb" and d.role in ("event_sensor", "rgb_camera"):
            lines += [what, f'SUBSYSTEM=="usb", {match}, GROUP="plugdev", MODE="0660"', ""]
    if n_trig == n_cam == 0 and len(lines) == 3:
        lines.append("# (no trigger box or camera with USB IDs was found; see deploy/udev/99-rigd.rules)")
    return "\n".join(lines).rstrip("\n") + "\n"
