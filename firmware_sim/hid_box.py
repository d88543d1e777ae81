"""The simulated trigger box as a raw-HID device: a fake of hidapi's `hid` module.

Some trigger boxes enumerate as HID instead of CDC serial (no driver on Windows, no
ModemManager probing on Linux). They carry the same line protocol in 64-byte reports
(framing in docs/trigger-protocol.md, *HID transport*). This module bridges such reports
to the unchanged sim firmware (`SimTriggerBox(link="socket")`), so the real
`drivers.trigger_link.HidTransport` is what the tests exercise.

`FakeHidApi` mimics the parts of hidapi's module the driver uses (`enumerate`, `device`),
listing every open socket-linked sim box; tests install it in place of `hid` to open
`hid://VID:PID/SERIAL` specs through the registry. `FakeHidDevice` mimics `hid.device`:
reads and writes of whole reports, `OSError("read error")` once the box is gone (what
hidapi raises when a device is unplugged).
"""

from __future__ import annotations

import logging
import select
import threading
from typing import Any

from firmware_sim.trigger_box import SimTriggerBox
from firmware_sim.trigger_commands import MODEL, VENDOR

log = logging.getLogger(__name__)

#: pid.codes test VID/PID: never a real product, so a sim box cannot shadow real hardware.
SIM_HID_VID = 0x1209
SIM_HID_PID = 0x0001
REPORT_SIZE = 64
PAYLOAD = REPORT_SIZE - 1

_boxes_lock = threading.Lock()
_boxes: dict[bytes, SimTriggerBox] = {}


def box_serial(box: SimTriggerBox) -> str:
    """The serial number the box reports over USB (matches its `ID?` reply)."""
    return f"SIM{box.seed:04d}"


def hid_path(box: SimTriggerBox) -> bytes:
    """hidapi identifies devices by an opaque byte path; the sim uses the world name."""
    return f"sim-hidraw:{box.world.name}".encode()


def attach(box: SimTriggerBox) -> bytes:
    """Make a socket-linked box visible to `FakeHidApi.enumerate`; returns its path."""
    if box.host_socket is None:
        raise ValueError(f"sim trigger box {box.port_path} has no socket link; create it with link='socket'")
    path = hid_path(box)
    with _boxes_lock:
        _boxes[path] = box
    return path


def _live_boxes() -> dict[bytes, SimTriggerBox]:
    with _boxes_lock:
        for path in [p for p, b in _boxes.items() if b.closed]:
            del _boxes[path]
        return dict(_boxes)


class FakeHidDevice:
    """hidapi `hid.device` look-alike bridging 64-byte reports to a sim box's byte link."""

    def __init__(self, box: SimTriggerBox | None = None) -> None:
        self._box: SimTriggerBox | None = None
        self._closed = False
        self.reports_in = 0
        self.reports_out = 0
        self._returned = 0  # bytes its reads returned (the box learns they were handled)
        if box is not None:
            self._bind(box)

    def _bind(self, box: SimTriggerBox) -> None:
        if box.host_socket is None:
            raise OSError(f"sim trigger box {box.port_path} has no socket link")
        self._box = box
        box.host_handled(0)  # from now on the box waits for this device's reports

    # -- opening, as hidapi does it
    def open_path(self, path: bytes) -> None:
        box = _live_boxes().get(bytes(path))
        if box is None:
            raise OSError(f"open failed: no sim HID device at {path!r}")
        self._bind(box)

    def open(self, vendor_id: int = 0, product_id: int = 0, serial_number: str | None = None) -> None:
        for box in _live_boxes().values():
            if (vendor_id, product_id) == (SIM_HID_VID, SIM_HID_PID) and serial_number in (
                None,
                box_serial(box),
            ):
                self._bind(box)
                return
        raise OSError("open failed")

    def _socket(self) -> Any:
        box = self._box
        if box is None or self._closed:
            raise ValueError("not open")
        if box.closed or box.host_socket is None:
            raise OSError("read error")  # unplugged: what hidapi says
        return box.host_socket

    # -- I/O
    def read(self, max_length: int, timeout_ms: int = 0) -> list[int]:
        sock = self._socket()
        box = self._box
        if box is not None:  # the driver reads again only once it handled what it got
            box.host_handled(self._returned)
        try:
            ready, _, _ = select.select([sock], [], [], max(timeout_ms, 0) / 1000.0)
            if not ready:
                return []
            data = sock.recv(min(PAYLOAD, max(max_length - 1, 0)))
        except (OSError, ValueError) as exc:  # socket closed under us: the box was unplugged
            raise OSError("read error") from exc
        if not data:
            raise OSError("read error")
        self.reports_in += 1
        self._returned += len(data)
        return [len(data), *data, *bytes(PAYLOAD - len(data))]

    def write(self, buff: bytes | list[int]) -> int:
        sock = self._socket()
        report = bytes(buff)
        if len(report) != REPORT_SIZE + 1 or report[0] != 0:
            raise ValueError(
                f"sim HID box takes report ID 0 + {REPORT_SIZE} bytes, got {len(report)} bytes "
                f"starting {report[:1].hex()}"
            )
        n = report[1]
        if n > PAYLOAD:
            log.warning("sim HID box: report with length byte %d dropped", n)
            return len(report)
        try:
            sock.sendall(report[2 : 2 + n])
        except OSError as exc:
            raise OSError("write error") from exc
        self.reports_out += 1
        return len(report)

    def set_nonblocking(self, enable: int) -> int:
        return 0

    def get_manufacturer_string(self) -> str:
        return VENDOR

    def get_product_string(self) -> str:
        return MODEL

    def get_serial_number_string(self) -> str:
        return box_serial(self._box) if self._box is not None else ""

    def close(self) -> None:
        self._closed = True


class FakeHidApi:
    """Stands in for hidapi's `hid` module (`enumerate`, `device`)."""

    @staticmethod
    def enumerate(vendor_id: int = 0, product_id: int = 0) -> list[dict[str, Any]]:
        out: list[dict[str, Any]] = []
        if vendor_id not in (0, SIM_HID_VID) or product_id not in (0, SIM_HID_PID):
            return out
        for path, box in sorted(_live_boxes().items()):
            out.append(
                {
                    "path": path,
                    "vendor_id": SIM_HID_VID,
                    "product_id": SIM_HID_PID,
                    "serial_number": box_serial(box),
                    "release_number": 0x0100,
                    "manufacturer_string": VENDOR,
                    "product_string": MODEL,
                    "usage_page": 0xFFAB,
                    "usage": 0x0200,
                    "interface_number": 0,
                }
            )
        return out

    @staticmethod
    def device() -> FakeHidDevice:
        return FakeHidDevice()
