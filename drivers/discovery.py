"""What is attached and usable: serial ports, USB devices, HID devices, V4L2 nodes, GenICam cameras.

Each source (`drivers.discovery_sources`) is a function returning `FoundDevice`s
(`drivers.found_devices`); a source that cannot run here (no libusb backend, no Aravis, no sysfs)
is reported as unavailable with the reason, never as an exception, so `rigd devices` always
prints what it could find. Sources are injectable (`discover(sources=...)`) so tests run without
hardware. What an operator installs from the result (rig-config skeleton, udev rules) is in
`drivers.device_setup`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping

from drivers.discovery_sources import (
    find_genicam_cameras,
    find_hid_devices,
    find_serial_ports,
    find_usb_devices,
    find_v4l2_nodes,
)
from drivers.found_devices import Discovery, FoundDevice, SourceReport, SourceUnavailable

log = logging.getLogger(__name__)


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
