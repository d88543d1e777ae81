"""Discovery with injected sources (no hardware needed), plus the real sources failing soft."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import pytest

from drivers.device_setup import config_skeleton, udev_rules, write_config_skeleton
from drivers.discovery import DEFAULT_SOURCES, discover
from drivers.discovery_sources import find_v4l2_nodes
from drivers.found_devices import FoundDevice, SourceUnavailable, lookup_usb
from rigd.app.config import RigConfig


def _teensy() -> FoundDevice:
    return FoundDevice(
        "serial",
        "Teensy",
        "trigger",
        "/dev/serial/by-id/usb-Teensy-if00",
        "/dev/ttyACM0",
        0x16C0,
        0x0483,
        "123",
    )


def _sources() -> dict[str, object]:
    def usb() -> list[FoundDevice]:
        return [
            FoundDevice(
                "usb",
                "EVK4",
                "event_sensor",
                "prophesee://00ABC",
                "usb:2:3",
                0x04B4,
                0x00F5,
                "00ABC",
                usb_speed_mbps=480,
            ),
            FoundDevice(
                "usb", "Teensy", "trigger", None, "usb:1:4", 0x16C0, 0x0483, "123", usb_speed_mbps=12
            ),
        ]

    def v4l2() -> list[FoundDevice]:
        return [
            FoundDevice("v4l2", "UVC cam", "rgb_camera", "v4l2:///dev/video0", "/dev/video0", 0x046D, 0x085B)
        ]

    def genicam() -> list[FoundDevice]:
        raise SourceUnavailable("Aravis is not available (test)")

    def hid() -> list[FoundDevice]:
        raise RuntimeError("hidapi exploded")

    return {"serial": lambda: [_teensy()], "usb": usb, "hid": hid, "v4l2": v4l2, "genicam": genicam}


def test_sources_fail_soft_and_duplicates_merge() -> None:
    found = discover(_sources())  # type: ignore[arg-type]
    by = {s.source: s for s in found.sources}
    assert not by["genicam"].available
    assert "Aravis" in by["genicam"].reason
    assert not by["hid"].available
    assert "RuntimeError: hidapi exploded" in by["hid"].reason
    # The Teensy seen by pyusb and as a serial port is listed once, with the USB link speed.
    assert [d.name for d in by["usb"].devices] == ["EVK4"]
    assert by["serial"].devices[0].usb_speed_mbps == 12
    assert not found.nothing_attached
    data = json.loads(found.to_json())
    assert data["sources"][1]["devices"][0]["usb_id"] == "04b4:00f5"
    assert data["sources"][1]["devices"][0]["usb_speed"] == "USB 2 (480 Mbit/s)"


def test_nothing_attached_is_plain() -> None:
    found = discover({"serial": list, "usb": list})
    assert found.nothing_attached
    assert json.loads(found.to_json())["nothing_attached"] is True


def test_real_sources_never_raise() -> None:
    found = discover(DEFAULT_SOURCES)
    assert [s.source for s in found.sources] == list(DEFAULT_SOURCES)
    for s in found.sources:
        assert s.available or s.reason


def test_known_usb_table() -> None:
    k = lookup_usb(0x16C0, 0x0486)
    assert k is not None
    assert k.role == "trigger"
    k2 = lookup_usb(0x2341, 0x0043)  # vendor-wide entry
    assert k2 is not None
    assert k2.label == "Arduino"
    assert lookup_usb(0x1234, 0x5678) is None
    assert lookup_usb(None, None) is None


@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_config_skeleton_loads_as_a_rig_config(tmp_path: Path, suffix: str) -> None:
    found = discover(_sources())  # type: ignore[arg-type]
    out = tmp_path / f"rig{suffix}"
    notes = write_config_skeleton(found, out)
    rig = RigConfig.load(out)
    assert rig.trigger.spec == "/dev/serial/by-id/usb-Teensy-if00"
    assert [c.spec for c in rig.cameras] == ["v4l2:///dev/video0"]
    assert rig.cameras[0].settings.trigger_mode == "free_run"
    assert [s.spec for s in rig.event_sensors] == ["prophesee://00ABC"]
    assert any("software-only" in n for n in notes)
    if suffix == ".toml":
        assert "software-only" in out.read_text()
        tomllib.loads(out.read_text())


def test_config_skeleton_with_nothing_found_says_what_to_edit() -> None:
    config, notes = config_skeleton(discover({}))
    assert config["trigger"]["spec"] == "/dev/rigd-trigger"
    assert any("no trigger box found" in n for n in notes)
    assert any("no camera or event sensor" in n for n in notes)
    with pytest.raises(ValueError, match=r"\.toml or \.json"):
        write_config_skeleton(discover({}), Path("rig.yaml"))


def test_udev_rules_give_stable_names() -> None:
    found = discover(_sources())  # type: ignore[arg-type]
    rules = udev_rules(found.devices)
    assert (
        'SUBSYSTEM=="tty", ATTRS{idVendor}=="16c0", ATTRS{idProduct}=="0483", ATTRS{serial}=="123", '
        'SYMLINK+="rigd-trigger"' in rules
    )
    assert 'SUBSYSTEM=="video4linux", ATTRS{idVendor}=="046d"' in rules
    assert 'SYMLINK+="rigd-cam0"' in rules
    assert 'SUBSYSTEM=="usb", ATTRS{idVendor}=="04b4", ATTRS{idProduct}=="00f5"' in rules
    assert "no trigger box or camera" in udev_rules([])


def test_v4l2_nodes_from_sysfs(tmp_path: Path) -> None:
    dev = tmp_path / "dev"
    dev.mkdir()
    sysfs = tmp_path / "sys"
    for n, index in (("video0", "0"), ("video1", "1")):
        (dev / n).touch()
        (sysfs / n).mkdir(parents=True)
        (sysfs / n / "name").write_text("HD Webcam\n")
        (sysfs / n / "index").write_text(index + "\n")
    nodes = find_v4l2_nodes(str(dev / "video*"), str(sysfs))
    assert [(d.name, d.role, d.spec) for d in nodes] == [
        ("HD Webcam", "rgb_camera", f"v4l2://{dev}/video0"),
        ("HD Webcam", "unknown", None),
    ]
    assert nodes[1].details["note"] == "metadata node"
