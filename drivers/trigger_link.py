"""The links a trigger box talks over: a byte `Transport` for the line protocol engine
(`drivers.serial_trigger`), over pyserial (CDC-ACM / UART boxes) or hidapi (boxes that
enumerate as HID, 64-byte reports carrying the same byte stream; framing in
docs/trigger-protocol.md). The engine needs nothing more than `read`, `write` and `close`.
"""

from __future__ import annotations

import abc
import importlib
import logging
import threading
from typing import Any, Protocol

import serial

from drivers.registry import DeviceSpec
from rigd.core.errors import BackendUnavailableError, ConfigError, DeviceError

log = logging.getLogger(__name__)

DEFAULT_BAUD = 115_200


class TransportError(DeviceError):
    """The link to the box failed (unplugged, I/O error): not a protocol problem."""


class Transport(abc.ABC):
    """A byte pipe to the box. The protocol engine needs nothing more than this."""

    #: Human-readable link name used in every message (port path, hid://VID:PID/SERIAL).
    name: str

    @abc.abstractmethod
    def read(self, timeout_s: float) -> bytes:
        """Bytes received so far, waiting at most `timeout_s` for the first; b"" on timeout.

        Raises TransportError when the link is gone (an unplugged device).
        """

    @abc.abstractmethod
    def write(self, data: bytes) -> None:
        """Send all of `data`; raises TransportError on failure."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the link. Idempotent; a blocked `read` returns or raises soon after."""


class SerialTransport(Transport):
    """pyserial link (USB CDC-ACM, FTDI/CH340 UART bridges, ptys)."""

    def __init__(self, port: str, *, baudrate: int = DEFAULT_BAUD) -> None:
        self.name = port
        self._closed = False
        try:
            self._ser = serial.serial_for_url(port, baudrate=baudrate, timeout=0.05, write_timeout=1.0)
        except (serial.SerialException, ValueError, OSError) as exc:
            raise DeviceError(f"cannot open trigger box port {port!r}: {exc}") from exc

    def read(self, timeout_s: float) -> bytes:
        # The port timeout is fixed at open (changing it per call costs a tcsetattr).
        try:
            return bytes(self._ser.read(max(1, self._ser.in_waiting)))
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            # TypeError/AttributeError: pyserial on a port closed under it.
            raise TransportError(f"trigger box {self.name}: serial read failed: {exc}") from exc

    def write(self, data: bytes) -> None:
        try:
            self._ser.write(data)
        except (serial.SerialException, OSError) as exc:
            raise TransportError(f"trigger box {self.name}: serial write failed: {exc}") from exc

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._ser.close()


#: Payload bytes of one HID report: 64 bytes minus the length byte.
HID_REPORT_SIZE = 64
HID_PAYLOAD = HID_REPORT_SIZE - 1


class HidDevice(Protocol):
    """The part of hidapi's `hid.device` the transport uses (the sim provides a fake)."""

    def read(self, max_length: int, timeout_ms: int = 0) -> list[int]: ...
    def write(self, buff: bytes | list[int]) -> int: ...
    def close(self) -> None: ...


def hid_report(payload: bytes) -> bytes:
    """One 64-byte report: length byte, up to 63 stream bytes, zero padding."""
    if len(payload) > HID_PAYLOAD:
        raise ValueError(f"HID report payload is {len(payload)} bytes, at most {HID_PAYLOAD} fit")
    return bytes([len(payload)]) + payload + bytes(HID_PAYLOAD - len(payload))


def hid_payload(report: bytes) -> bytes | None:
    """The stream bytes of a report, or None when its length byte is impossible."""
    if not report:
        return b""
    n = report[0]
    if n > HID_PAYLOAD or n > len(report) - 1:
        return None
    return bytes(report[1 : 1 + n])


class HidTransport(Transport):
    """The line protocol in 64-byte HID reports (hidapi).

    Report framing (docs/trigger-protocol.md, *HID transport*): byte 0 is the number of
    stream bytes that follow (0..63), the rest is padding. Reports are written with report
    ID 0 prepended, as hidapi wants for devices without numbered reports. Lines may span
    reports; a report with an impossible length byte is dropped and counted.
    """

    def __init__(self, device: HidDevice, name: str) -> None:
        self.name = name
        self._dev = device
        self._closed = False
        self._lock = threading.Lock()  # hidapi handles are not thread-safe between read and close
        self.bad_reports = 0

    def read(self, timeout_s: float) -> bytes:
        if self._closed:
            raise TransportError(f"trigger box {self.name}: HID device is closed")
        try:
            data = self._dev.read(HID_REPORT_SIZE, max(1, int(timeout_s * 1000)))
        except (OSError, ValueError) as exc:  # hidapi raises OSError("read error") on unplug
            raise TransportError(f"trigger box {self.name}: HID read failed (unplugged?): {exc}") from exc
        if not data:
            return b""
        payload = hid_payload(bytes(data))
        if payload is None:
            self.bad_reports += 1
            log.warning("trigger box %s: dropped HID report with length byte %d", self.name, data[0])
            return b""
        return payload

    def write(self, data: bytes) -> None:
        if self._closed:
            raise TransportError(f"trigger box {self.name}: HID device is closed")
        for i in range(0, max(len(data), 1), HID_PAYLOAD):
            report = b"\x00" + hid_report(data[i : i + HID_PAYLOAD])
            try:
                n = self._dev.write(report)
            except (OSError, ValueError) as exc:
                raise TransportError(f"trigger box {self.name}: HID write failed: {exc}") from exc
            if n < 0:
                raise TransportError(f"trigger box {self.name}: HID write failed (returned {n})")

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._dev.close()


def _import_hid() -> Any:
    """hidapi's `hid` module; optional, so a serial-only rig needs no HID library."""
    try:
        return importlib.import_module("hid")
    except ImportError as exc:
        raise BackendUnavailableError(
            f"hid:// trigger boxes need hidapi (`pip install hidapi`, libhidapi-hidraw0): {exc}"
        ) from exc


def parse_hid_address(spec: DeviceSpec) -> tuple[int, int, str | None]:
    """(vid, pid, serial) of `hid://VID:PID[/SERIAL]`, hex IDs as lsusb prints them."""
    vid_text, sep, pid_text = spec.location.partition(":")
    try:
        if not sep:
            raise ValueError
        vid, pid = int(vid_text, 16), int(pid_text, 16)
    except ValueError:
        raise ConfigError(
            f"device spec {spec.raw!r}: expected hid://VID:PID[/SERIAL] with hex IDs, e.g. hid://16c0:0486"
        ) from None
    if not (0 <= vid <= 0xFFFF and 0 <= pid <= 0xFFFF):
        raise ConfigError(f"device spec {spec.raw!r}: USB IDs are 16-bit hex numbers")
    serial_nbr = spec.path.strip("/") or None
    return vid, pid, serial_nbr


def open_hid_transport(vid: int, pid: int, serial_nbr: str | None, hid_module: Any = None) -> HidTransport:
    """Find and open the HID box; errors name the IDs and what was found instead."""
    hid = hid_module if hid_module is not None else _import_hid()
    name = f"hid://{vid:04x}:{pid:04x}" + (f"/{serial_nbr}" if serial_nbr else "")
    found = [d for d in hid.enumerate(vid, pid) if serial_nbr is None or d.get("serial_number") == serial_nbr]
    if not found:
        others = sorted({str(d.get("serial_number") or "?") for d in hid.enumerate(vid, pid)})
        hint = (
            f"; serial numbers present: {', '.join(others)}"
            if others
            else " (is it plugged in? see `rigd devices`)"
        )
        raise DeviceError(f"cannot open trigger box {name}: no such HID device{hint}")
    if len(found) > 1 and serial_nbr is None:
        serials = ", ".join(str(d.get("serial_number") or "?") for d in found)
        raise ConfigError(f"trigger box {name}: {len(found)} devices match; add /SERIAL (one of {serials})")
    dev = hid.device()
    try:
        dev.open_path(found[0]["path"])
    except (OSError, ValueError) as exc:
        raise DeviceError(
            f"cannot open trigger box {name} ({found[0]['path']!r}): {exc}; "
            "check the hidraw node permissions (`rigd doctor`, deploy/udev/99-rigd.rules)"
        ) from exc
    return HidTransport(dev, name)
