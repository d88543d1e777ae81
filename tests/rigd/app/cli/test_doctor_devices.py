"""`rigd doctor` and `rigd devices` tell one truth about a backend: both read the same discovery."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

import drivers.discovery as discovery
from drivers.found_devices import FoundDevice, SourceUnavailable
from rigd.app.cli import app

REASON = "pyusb has no libusb backend (No backend available); apt-get install libusb-1.0-0"


@pytest.fixture
def no_libusb(monkeypatch: pytest.MonkeyPatch) -> None:
    def find_usb() -> list[FoundDevice]:
        raise SourceUnavailable(REASON)

    monkeypatch.setitem(discovery.DEFAULT_SOURCES, "usb", find_usb)


@pytest.mark.usefixtures("no_libusb")
def test_doctor_and_devices_agree_that_usb_is_unusable() -> None:
    runner = CliRunner()
    devices = runner.invoke(app, ["devices", "--local"])
    assert devices.exit_code == 0, devices.output
    assert f"usb: unavailable ({REASON})" in " ".join(devices.stdout.split())
    doctor = runner.invoke(app, ["doctor", "--json", "--no-disk-test"])
    assert doctor.exit_code in (0, 1), doctor.output
    usb = next(c for c in json.loads(doctor.stdout)["checks"] if c["name"] == "backend usb")
    assert usb["status"] == "WARN"
    assert REASON in usb["message"]


def test_doctor_says_ok_only_where_devices_can_look(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(discovery.DEFAULT_SOURCES, "usb", lambda: [])
    doctor = CliRunner().invoke(app, ["doctor", "--json", "--no-disk-test"])
    usb = next(c for c in json.loads(doctor.stdout)["checks"] if c["name"] == "backend usb")
    assert usb["status"] == "OK"
    assert usb["message"] == "usable (0 device(s) found)"
