"""`rigd doctor` with injected readings, and `rigd devices` / `rigd doctor` on this machine."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from drivers.found_devices import Discovery, FoundDevice, SourceReport
from rigd.app.commands.devices import devices
from rigd.app.commands.doctor import doctor
from rigd.app.config import RigConfig, default_sim_rig
from rigd.app.doctor import Check, run_checks, summary_status
from rigd.app.doctor_readings import NodeAccess, Readings
from rigd.app.rig_plan import plan_rig

RIG = {
    "trigger": {"spec": "/dev/rigd-trigger", "settings": {"rate_hz": 60.0, "pulse_width_us": 500}},
    "cameras": [
        {
            "name": "cam0",
            "spec": "genicam://ABC?width=2048&height=1536",
            "settings": {"pixel_format": "mono8"},
        },
        {
            "name": "cam1",
            "spec": "v4l2:///dev/video0?width=640&height=480",
            "settings": {"trigger_mode": "free_run"},
        },
    ],
    "event_sensors": [{"name": "ev0", "spec": "prophesee://X", "settings": {"erc_rate_ev_s": 5e6}}],
}


def _healthy(**over: object) -> Readings:
    found = Discovery(
        [
            SourceReport(
                "usb",
                True,
                [
                    FoundDevice(
                        "usb",
                        "EVK4",
                        "event_sensor",
                        "prophesee://X",
                        "usb:1:2",
                        0x04B4,
                        0x00F5,
                        usb_speed_mbps=5000,
                    )
                ],
            )
        ]
    )
    r = Readings(
        usbfs_memory_mb=lambda: 1000,
        free_disk_bytes=lambda p: 10**13,
        disk_write_mb_s=lambda p: 2000.0,
        clocksource=lambda: ("tsc", ["tsc", "hpet"]),
        rmem_max=lambda: 64 << 20,
        user_groups=lambda: {"dialout", "video", "plugdev"},
        is_root=lambda: False,
        node_access=lambda p: NodeAccess(True, True, True),
        udev_rules=lambda: ["/etc/udev/rules.d/99-rigd.rules"],
        discovery=lambda: found,
        module_reason=lambda m: None,
        hdf5_filters=lambda: {"lz4": True, "zstd": True, "gzip": True},
    )
    for k, v in over.items():
        setattr(r, k, v)
    return r


def _by_name(checks: list[Check]) -> dict[str, Check]:
    return {c.name: c for c in checks}


@pytest.fixture
def rig() -> RigConfig:
    return RigConfig.from_data(RIG)


def test_plan_rig(rig: RigConfig) -> None:
    plan = plan_rig(rig)
    cam0 = 2048 * 1536 * 60
    cam1 = 640 * 480 * 3 * 30
    assert plan.bytes_per_s == pytest.approx(cam0 + cam1 + 5e6 * 13)
    assert plan.usb_cameras == [("cam0", 2048 * 1536)]
    assert plan.event_sensors_usb == 1
    assert plan.gige_cameras == ["cam0"]
    assert plan.node_paths == ["/dev/rigd-trigger", "/dev/video0"]


def test_healthy_machine_is_all_ok(rig: RigConfig) -> None:
    checks = run_checks(_healthy(), rig=rig, duration_s=60)
    assert summary_status(checks) == "OK", [c.line() for c in checks if c.status != "OK"]


def test_too_small_usbfs_limit_fails_with_the_fix(rig: RigConfig) -> None:
    c = _by_name(run_checks(_healthy(usbfs_memory_mb=lambda: 16), rig=rig))["usbfs memory"]
    assert c.status == "FAIL"
    assert "limit 16 MB < 112 MB" in c.message  # 16 x 3 MiB frames + 64 MB for the EVK
    assert "usbfs_memory_mb" in c.fix
    assert "usbcore.usbfs_memory_mb=1000" in c.fix


def test_too_slow_disk_fails(rig: RigConfig) -> None:
    c = _by_name(run_checks(_healthy(disk_write_mb_s=lambda p: 50.0), rig=rig))["disk write speed"]
    assert c.status == "FAIL"
    assert "50 MB/s measured" in c.message
    assert "overflow" in c.message


def test_too_little_free_disk(rig: RigConfig) -> None:
    checks = _by_name(run_checks(_healthy(free_disk_bytes=lambda p: 10**9), rig=rig, duration_s=600))
    assert checks["free disk"].status == "FAIL"
    assert "needs ~" in checks["free disk"].message


def test_permissions_groups_speed_clock_buffers_backends(rig: RigConfig) -> None:
    slow_usb = Discovery(
        [
            SourceReport(
                "usb",
                True,
                [
                    FoundDevice(
                        "usb",
                        "EVK4",
                        "event_sensor",
                        "prophesee://X",
                        None,
                        0x04B4,
                        0x00F5,
                        usb_speed_mbps=480,
                    )
                ],
            )
        ]
    )
    r = _healthy(
        node_access=lambda p: NodeAccess(p != "/dev/video0", True, p != "/dev/rigd-trigger"),
        udev_rules=lambda: [],
        user_groups=lambda: {"video"},
        discovery=lambda: slow_usb,
        clocksource=lambda: ("hpet", ["hpet", "acpi_pm"]),
        rmem_max=lambda: 212992,
        module_reason=lambda m: "No module named 'metavision_hal'" if m == "metavision_hal" else None,
        hdf5_filters=lambda: {"lz4": False, "zstd": True, "gzip": True},
    )
    checks = _by_name(run_checks(r, rig=rig, disk_test=False))
    assert checks["node /dev/rigd-trigger"].status == "FAIL"
    assert "permission" in checks["node /dev/rigd-trigger"].message
    assert checks["node /dev/video0"].status == "FAIL"
    assert "does not exist" in checks["node /dev/video0"].message
    assert checks["udev rules"].status == "WARN"
    assert checks["groups"].status == "WARN"
    assert "usermod -aG dialout,plugdev" in checks["groups"].fix
    assert checks["usb link EVK4 (prophesee://X)"].status == "WARN"
    assert checks["clock source"].status == "WARN"
    assert "unstable TSC" in checks["clock source"].fix
    assert checks["socket buffers"].status == "WARN"
    assert "net.core.rmem_max=33554432" in checks["socket buffers"].fix
    assert checks["hdf5 plugins"].status == "FAIL"
    assert checks["backend prophesee"].status == "FAIL"
    assert checks["backend genicam"].status == "OK"
    assert "disk write speed" not in checks


def test_a_reading_that_fails_is_a_warn_not_a_crash(rig: RigConfig) -> None:
    def boom() -> int:
        raise PermissionError("denied")

    c = _by_name(run_checks(_healthy(usbfs_memory_mb=boom), rig=rig))["usbfs memory"]
    assert c.status == "WARN"
    assert "could not be checked: PermissionError: denied" in c.message


def _app() -> typer.Typer:
    app = typer.Typer()
    app.command("devices")(devices)
    app.command("doctor")(doctor)
    return app


def test_devices_cli_json_and_outputs(tmp_path: Path) -> None:
    res = CliRunner().invoke(
        _app(),
        ["devices", "--json", "--config", str(tmp_path / "rig.toml"), "--udev", str(tmp_path / "r.rules")],
    )
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout)
    assert {s["source"] for s in data["sources"]} == {"serial", "usb", "hid", "v4l2", "genicam"}
    assert (tmp_path / "rig.toml").exists()
    assert (tmp_path / "r.rules").read_text().startswith("# Generated by `rigd devices --udev`")


def test_devices_cli_says_plainly_when_nothing_is_attached(monkeypatch: pytest.MonkeyPatch) -> None:
    import drivers.discovery as mod  # the command imports it when it runs

    monkeypatch.setattr(mod, "discover", lambda: Discovery([SourceReport("usb", False, reason="no libusb")]))
    res = CliRunner().invoke(_app(), ["devices"])
    assert res.exit_code == 0
    assert "nothing usable is attached" in res.stdout
    assert "usb: unavailable (no libusb)" in res.stdout


def test_devices_config_notes_keep_their_toml_table_names(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The skeleton's notes name TOML tables; they must not be eaten as console markup."""
    import drivers.discovery as mod  # the command imports it when it runs

    monkeypatch.setattr(mod, "discover", lambda: Discovery([SourceReport("usb", False, reason="no libusb")]))
    res = CliRunner().invoke(_app(), ["devices", "--config", str(tmp_path / "skel.toml")])
    assert res.exit_code == 0, res.output
    assert "add [[cameras]] / [[event_sensors]] before capturing" in res.stderr
    assert "add [] / []" not in res.stderr


def test_doctor_cli_json_on_this_machine(tmp_path: Path) -> None:
    res = CliRunner().invoke(_app(), ["doctor", "--json", "--no-disk-test", "--out", str(tmp_path)])
    assert res.exit_code in (0, 1), res.output
    data = json.loads(res.stdout)
    assert data["status"] in ("OK", "WARN", "FAIL")
    assert {c["status"] for c in data["checks"]} <= {"OK", "WARN", "FAIL"}
    names = [c["name"] for c in data["checks"]]
    assert "usbfs memory" in names
    assert "clock source" in names


def test_doctor_cli_bad_config(tmp_path: Path) -> None:
    bad = tmp_path / "rig.toml"
    bad.write_text("nonsense = [")
    res = CliRunner().invoke(_app(), ["doctor", "--config", str(bad)])
    assert res.exit_code == 2


def test_bayer_cameras_are_planned_at_one_byte_per_pixel() -> None:
    plans = {f: plan_rig(default_sim_rig(pixel_format=f)) for f in ("rgb8", "bayer_rg8", "mono8")}
    cams = {
        f: p.bytes_per_s
        - plan_rig(default_sim_rig(pixel_format=f).model_copy(update={"cameras": []})).bytes_per_s
        for f, p in plans.items()
    }
    assert cams["rgb8"] == pytest.approx(3 * 1280 * 720 * 3 * 30.0)
    assert cams["bayer_rg8"] == pytest.approx(cams["rgb8"] / 3)
    assert cams["mono8"] == pytest.approx(cams["bayer_rg8"])


@pytest.mark.slow
def test_the_trigger_box_check_lets_the_box_pulse_and_reads_its_counters() -> None:
    from uuid import uuid4

    from firmware_sim.world import reset_world
    from rigd.app.doctor import TRIGGER_TEST_PULSES, check_trigger_box

    world = f"doctor-{uuid4().hex[:8]}"
    try:
        rig = default_sim_rig(world=world)
        [check] = check_trigger_box(rig)
        assert check.status == "OK", check
        assert "trigbox-sim" in check.message
        assert f"{TRIGGER_TEST_PULSES} pulses at 30 Hz, every record on its schedule" in check.message
        assert "records_dropped=0" in check.message
        rig.trigger.spec = f"sim://{world}/trigger?drop_pulses=3&garbage_after=1"
        [check] = check_trigger_box(rig)
        assert check.status == "FAIL", check  # a record it cannot get back is a failed box
    finally:
        reset_world(world)


def test_the_trigger_box_check_names_a_port_it_cannot_open(tmp_path: Path) -> None:
    from rigd.app.doctor import check_trigger_box

    rig = RigConfig.model_validate({**RIG, "trigger": {"spec": f"serial://{tmp_path}/ttyNONE"}})
    [check] = check_trigger_box(rig)
    assert check.status == "FAIL"
    assert "ttyNONE" in check.message
    assert "cannot open it" in check.message
