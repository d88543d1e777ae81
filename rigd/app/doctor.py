"""`rigd doctor`: what on this machine will stop a take, each as OK / WARN / FAIL with the fix.

Every reading (usbfs limit, free disk, write speed, clock source, groups, ...) comes from a
`Readings` object of provider functions (`rigd.app.doctor_readings`), so tests simulate a
too-small usbfs limit or a slow disk without touching the machine; `Readings()` reads the real
one. Checks never raise: a reading that fails becomes a WARN saying it could not be read. The
rig's data rates the checks compare against come from `rigd.app.rig_plan`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

from drivers.found_devices import Discovery, SourceReport
from rigd.app.config import RigConfig
from rigd.app.doctor_readings import Readings
from rigd.app.rig_plan import Plan, plan_rig, spec_or_none
from rigd.core.errors import ConfigError

log = logging.getLogger(__name__)

Status = Literal["OK", "WARN", "FAIL"]

#: Buffers a userspace USB camera driver (Aravis U3V, libusb) keeps queued per camera.
USB_BUFFERS_PER_CAMERA = 16
#: usbfs memory a Prophesee EVK's libusb transfers take (bulk transfer ring).
USBFS_MB_PER_EVENT_SENSOR = 64
#: GigE Vision streams need large socket buffers or the kernel drops packets at line rate.
GIGE_RMEM_MIN = 32 * 1024 * 1024
RECOMMENDED_USBFS_MB = 1000
GROUPS = {"dialout": "serial trigger boxes", "video": "V4L2 cameras", "plugdev": "USB/HID devices"}
GOOD_CLOCKSOURCES = {"tsc", "arch_sys_counter", "kvm-clock", "hyperv_clocksource_tsc_page"}


@dataclass(frozen=True, slots=True)
class Check:
    name: str
    status: Status
    message: str
    fix: str = ""

    def line(self) -> str:
        text = f"{self.status:<4} {self.name}: {self.message}"
        return f"{text}\n     -> {self.fix}" if self.fix and self.status != "OK" else text


def _guard(name: str, fn: Callable[[], list[Check]]) -> list[Check]:
    try:
        return fn()
    except Exception as exc:
        log.debug("doctor check %s failed", name, exc_info=True)
        return [Check(name, "WARN", f"could not be checked: {type(exc).__name__}: {exc}")]


def run_checks(
    readings: Readings | None = None,
    rig: RigConfig | None = None,
    out_dir: Path = Path("takes"),
    duration_s: float = 600.0,
    disk_test: bool = True,
    trigger_test: bool = False,
) -> list[Check]:
    """Every check, in the order an operator would fix them."""
    r = readings or Readings()
    plan = plan_rig(rig) if rig is not None else None
    found_holder: list[Discovery] = []

    def found() -> Discovery:
        if not found_holder:
            found_holder.append(r.discovery())
        return found_holder[0]

    checks: list[Check] = []
    checks += _guard("devices", lambda: _check_devices(found()))
    checks += _guard("device nodes", lambda: _check_nodes(r, found(), plan))
    checks += _guard("udev rules", lambda: _check_udev(r))
    checks += _guard("groups", lambda: _check_groups(r))
    checks += _guard("usb link speed", lambda: _check_usb_speed(found()))
    checks += _guard("usbfs memory", lambda: _check_usbfs(r, plan))
    checks += _guard("free disk", lambda: _check_free_disk(r, plan, out_dir, duration_s))
    if disk_test:
        checks += _guard("disk write speed", lambda: _check_write_speed(r, plan, out_dir))
    checks += _guard("clock source", lambda: _check_clocksource(r))
    checks += _guard("socket buffers", lambda: _check_rmem(r, plan))
    checks += _guard("hdf5 plugins", lambda: _check_hdf5(r, rig))
    checks += _guard("backends", lambda: _check_backends(r, rig, found()))
    if trigger_test and rig is not None:
        checks += _guard("trigger box", lambda: check_trigger_box(rig))
    return checks


#: Pulses the trigger-box check asks for (a third of a second at the default 30 Hz).
TRIGGER_TEST_PULSES = 10


def check_trigger_box(rig: RigConfig) -> list[Check]:
    """Open the rig's trigger box with the real driver and let it pulse: its identity, that
    every pulse record arrives on the documented schedule, and the box's own counters.

    The cameras and sensors on the trigger line see TRIGGER_TEST_PULSES pulses."""
    from drivers.registry import open_device
    from rigd.core.errors import DeviceError, ProtocolError
    from rigd.core.timebase import pulse_offset_us

    name = "trigger box"
    spec = rig.trigger.spec
    try:
        trig = open_device("trigger", spec)
    except (ConfigError, DeviceError) as exc:
        return [Check(name, "FAIL", f"{spec}: cannot open it: {exc}", _TRIGGER_FIX)]
    try:
        info = trig.info
        who = f"{info.vendor} {info.model} serial {info.serial} firmware {info.firmware} on {spec}"
        settings = rig.trigger.settings
        trig.configure(settings)
        trig.arm()
        t0 = trig.start(TRIGGER_TEST_PULSES)
        deadline = time.monotonic() + TRIGGER_TEST_PULSES / settings.rate_hz + 5.0
        got: dict[int, int] = {}
        while len(got) < TRIGGER_TEST_PULSES and time.monotonic() < deadline:
            batch = trig.read_pulses(0.1)
            got.update(zip(batch.index.tolist(), batch.t_us.tolist(), strict=True))
        trig.stop()
        want = {k: t0 + pulse_offset_us(k, settings.rate_hz) for k in range(TRIGGER_TEST_PULSES)}
        if got != want:
            wrong = sorted(k for k in want if got.get(k) != want[k])
            return [
                Check(
                    name,
                    "FAIL",
                    f"{who}: pulse records {wrong[:10]} missing or off the schedule "
                    f"t0 + round(k * 1e6 / {settings.rate_hz:g}) (docs/trigger-protocol.md)",
                    _TRIGGER_FIX,
                )
            ]
        counters = ""
        if link := trig.link_stats():
            counters = (
                f"; link: {link.get('corrupt_lines', 0)} corrupt lines, {link.get('retries', 0)} retries"
            )
        try:
            if diag := trig.diag():
                counters += "; box: " + ", ".join(f"{k}={v}" for k, v in diag.items())
        except ProtocolError as exc:  # a v1 box has no DIAG?
            log.debug("trigger box %s has no DIAG?: %s", spec, exc)
        return [
            Check(
                name,
                "OK",
                f"{who}: {TRIGGER_TEST_PULSES} pulses at {settings.rate_hz:g} Hz, every record on "
                f"its schedule{counters}",
            )
        ]
    except (DeviceError, ProtocolError) as exc:
        return [Check(name, "FAIL", f"{spec}: {exc}", _TRIGGER_FIX)]
    finally:
        trig.close()


_TRIGGER_FIX = (
    "check the cable and the port, that no daemon holds it (rigd status), that the config's ?baud= "
    "matches the firmware build (docs/hardware.md), and reflash the box"
)


def _check_devices(found: Discovery) -> list[Check]:
    if found.nothing_attached:
        return [
            Check(
                "devices",
                "WARN",
                "no camera, event sensor or trigger box is attached",
                "plug the devices in, then run `rigd devices`",
            )
        ]
    roles = {role: len(found.by_role(role)) for role in ("trigger", "rgb_camera", "event_sensor")}
    return [Check("devices", "OK", ", ".join(f"{n} {role}" for role, n in roles.items()))]


def _check_nodes(r: Readings, found: Discovery, plan: Plan | None) -> list[Check]:
    paths = [d.path for d in found.devices if d.path and d.path.startswith("/dev/")]
    paths += [p for p in (plan.node_paths if plan else []) if p.startswith("/dev/")]
    out: list[Check] = []
    for path in dict.fromkeys(paths):
        acc = r.node_access(path)
        if not acc.exists:
            out.append(
                Check(
                    f"node {path}",
                    "FAIL",
                    "does not exist (unplugged, or a wrong name in the config)",
                    "plug the device in; `rigd devices` lists the names that exist",
                )
            )
        elif not (acc.readable and acc.writable):
            out.append(
                Check(
                    f"node {path}",
                    "FAIL",
                    "no read/write permission for this user",
                    "install the udev rules (`rigd devices --udev 99-rigd.rules`) or join the "
                    "device's group (see the groups check), then replug",
                )
            )
        else:
            out.append(Check(f"node {path}", "OK", "readable and writable"))
    if not out:
        out.append(Check("device nodes", "OK", "no device node to check"))
    return out


def _check_udev(r: Readings) -> list[Check]:
    rules = r.udev_rules()
    if rules:
        return [Check("udev rules", "OK", "installed: " + ", ".join(rules))]
    return [
        Check(
            "udev rules",
            "WARN",
            "no rigd udev rules installed: device names may change between boots",
            "rigd devices --udev 99-rigd.rules && sudo cp 99-rigd.rules /etc/udev/rules.d/ && "
            "sudo udevadm control --reload && sudo udevadm trigger",
        )
    ]


def _check_groups(r: Readings) -> list[Check]:
    if r.is_root():
        return [
            Check(
                "groups",
                "OK",
                "running as root (run the daemon as a user in dialout, video, plugdev instead)",
            )
        ]
    have = r.user_groups()
    missing = {g: why for g, why in GROUPS.items() if g not in have}
    if not missing:
        return [Check("groups", "OK", "member of " + ", ".join(GROUPS))]
    what = ", ".join(f"{g} ({why})" for g, why in missing.items())
    return [
        Check(
            "groups",
            "WARN",
            f"not in {what}",
            f"sudo usermod -aG {','.join(missing)} $USER, then log out and back in",
        )
    ]


def _check_usb_speed(found: Discovery) -> list[Check]:
    out: list[Check] = []
    for d in found.devices:
        if d.usb_speed_mbps is None or d.role not in ("rgb_camera", "event_sensor"):
            continue
        label = f"{d.name} ({d.spec or d.path})"
        if d.usb_speed_mbps >= 5000:
            out.append(Check(f"usb link {label}", "OK", f"{d.usb_speed_mbps} Mbit/s (USB 3)"))
        elif d.source == "v4l2" and d.usb_speed_mbps >= 480:
            out.append(Check(f"usb link {label}", "OK", f"{d.usb_speed_mbps} Mbit/s (USB 2, enough for UVC)"))
        else:
            out.append(
                Check(
                    f"usb link {label}",
                    "WARN" if d.usb_speed_mbps >= 480 else "FAIL",
                    f"{d.usb_speed_mbps} Mbit/s: a USB 2 link (or slower) caps the frame rate",
                    "use a USB 3 port (blue, or SS-marked) and a USB 3 cable, no USB 2 hub",
                )
            )
    if not out:
        out.append(Check("usb link speed", "OK", "no USB camera or event sensor with a known link speed"))
    return out


def _check_usbfs(r: Readings, plan: Plan | None) -> list[Check]:
    limit = r.usbfs_memory_mb()
    need_mb = 0
    if plan is not None:
        cams = sum(b * USB_BUFFERS_PER_CAMERA for _, b in plan.usb_cameras)
        need_mb = -(-cams // (1 << 20)) + USBFS_MB_PER_EVENT_SENSOR * plan.event_sensors_usb
    fix = (
        f"echo {max(RECOMMENDED_USBFS_MB, 2 * need_mb)} | sudo tee "
        "/sys/module/usbcore/parameters/usbfs_memory_mb; to keep it, add "
        f"usbcore.usbfs_memory_mb={max(RECOMMENDED_USBFS_MB, 2 * need_mb)} to the kernel command line"
    )
    if limit is None:
        return [Check("usbfs memory", "WARN", "cannot read /sys/module/usbcore/parameters/usbfs_memory_mb")]
    if limit == 0:
        return [Check("usbfs memory", "OK", "unlimited (0)")]
    if need_mb and limit < need_mb:
        return [
            Check(
                "usbfs memory",
                "FAIL",
                f"limit {limit} MB < {need_mb} MB the configured USB cameras/sensors need "
                f"({USB_BUFFERS_PER_CAMERA} buffers per camera): streams will stall or drop",
                fix,
            )
        ]
    if limit < RECOMMENDED_USBFS_MB and need_mb:
        return [
            Check(
                "usbfs memory",
                "WARN",
                f"limit {limit} MB covers the {need_mb} MB needed with little margin",
                fix,
            )
        ]
    what = f"covers the {need_mb} MB needed" if need_mb else "no userspace-USB camera configured"
    return [Check("usbfs memory", "OK", f"limit {limit} MB; {what}")]


def _check_free_disk(r: Readings, plan: Plan | None, out_dir: Path, duration_s: float) -> list[Check]:
    free = r.free_disk_bytes(out_dir)
    if plan is None:
        return [
            Check("free disk", "OK", f"{free / 1e9:.1f} GB free at {out_dir} (no rig config to size a take)")
        ]
    need = plan.bytes_per_s * duration_s
    msg = (
        f"{free / 1e9:.1f} GB free at {out_dir}; a {duration_s:g} s take needs ~{need / 1e9:.1f} GB "
        f"({plan.bytes_per_s / 1e6:.0f} MB/s before compression)"
    )
    fix = "free space, point --out at a larger disk, or plan shorter takes"
    if free < need:
        return [Check("free disk", "FAIL", msg, fix)]
    if free < 2 * need:
        return [Check("free disk", "WARN", msg + ": room for less than two takes", fix)]
    return [Check("free disk", "OK", msg)]


def _check_write_speed(r: Readings, plan: Plan | None, out_dir: Path) -> list[Check]:
    mb_s = r.disk_write_mb_s(out_dir)
    if plan is None:
        return [Check("disk write speed", "OK", f"{mb_s:.0f} MB/s at {out_dir}")]
    need = plan.bytes_per_s / 1e6
    msg = f"{mb_s:.0f} MB/s measured at {out_dir}; the rig produces ~{need:.0f} MB/s"
    fix = "write takes to a faster disk (NVMe SSD), enable compression, or lower rates/resolution"
    if mb_s < need:
        return [
            Check("disk write speed", "FAIL", msg + ": the writer queue will overflow and drop data", fix)
        ]
    if mb_s < 1.5 * need:
        return [Check("disk write speed", "WARN", msg + ": less than 50% headroom", fix)]
    return [Check("disk write speed", "OK", msg)]


def _check_clocksource(r: Readings) -> list[Check]:
    cs = r.clocksource()
    if cs is None:
        return [Check("clock source", "WARN", "cannot read /sys/devices/system/clocksource/clocksource0")]
    current, available = cs
    if current in GOOD_CLOCKSOURCES:
        return [Check("clock source", "OK", f"{current}")]
    fix = (
        "the kernel fell back from tsc (often an unstable TSC); check `dmesg | grep -i clocksource`"
        if "tsc" not in available
        else "echo tsc | sudo tee /sys/devices/system/clocksource/clocksource0/current_clocksource"
    )
    return [
        Check(
            "clock source",
            "WARN",
            f"{current}: slow clock reads make host timestamps (pulse matching) noisier",
            fix,
        )
    ]


def _check_rmem(r: Readings, plan: Plan | None) -> list[Check]:
    rmem = r.rmem_max()
    gige = plan.gige_cameras if plan else []
    if rmem is None:
        return [Check("socket buffers", "WARN", "cannot read /proc/sys/net/core/rmem_max")]
    fix = (
        f"sudo sysctl -w net.core.rmem_max={GIGE_RMEM_MIN}; to keep it, put "
        f"net.core.rmem_max={GIGE_RMEM_MIN} in /etc/sysctl.d/60-rigd.conf"
    )
    if rmem >= GIGE_RMEM_MIN:
        return [Check("socket buffers", "OK", f"net.core.rmem_max = {rmem}")]
    if gige:
        return [
            Check(
                "socket buffers",
                "WARN",
                f"net.core.rmem_max = {rmem} < {GIGE_RMEM_MIN}: GigE Vision streams of "
                f"{', '.join(gige)} will lose packets at full rate",
                fix,
            )
        ]
    return [Check("socket buffers", "OK", f"net.core.rmem_max = {rmem} (only GigE Vision cameras need more)")]


def _check_hdf5(r: Readings, rig: RigConfig | None) -> list[Check]:
    avail = r.hdf5_filters()
    wanted = {rig.writer.event_compression, rig.writer.frame_compression} - {"none"} if rig else set()
    missing = sorted(f for f in wanted if not avail.get(f, False))
    have = ", ".join(f for f, ok in avail.items() if ok) or "none"
    if missing:
        return [
            Check(
                "hdf5 plugins",
                "FAIL",
                f"the config compresses with {', '.join(missing)}, "
                f"which HDF5 cannot use here (available: {have})",
                "pip install hdf5plugin",
            )
        ]
    if not all(avail.values()):
        return [Check("hdf5 plugins", "WARN", f"available filters: {have}", "pip install hdf5plugin")]
    return [Check("hdf5 plugins", "OK", f"filters {have}")]


_BACKENDS = {
    "prophesee": ("metavision_hal", "OpenEB (Prophesee) Python bindings: https://docs.prophesee.ai"),
    "genicam": ("Aravis", "apt-get install gir1.2-aravis-0.8 && pip install PyGObject"),
    "v4l2": ("cv2", "pip install opencv-contrib-python-headless"),
    "hid": ("hid", "pip install hidapi (and apt-get install libhidapi-hidraw0)"),
    "usb": ("usb", "pip install pyusb (and apt-get install libusb-1.0-0)"),
}


def _check_backends(r: Readings, rig: RigConfig | None, found: Discovery | None = None) -> list[Check]:
    """A backend `rigd devices` also looks through is judged by that same look (its source report:
    pyusb importable but without a libusb backend is unusable, for both commands); the others by
    whether their module imports."""
    used: set[str] = set()
    if rig is not None:
        for spec_text in [
            rig.trigger.spec,
            *(c.spec for c in rig.cameras),
            *(s.spec for s in rig.event_sensors),
        ]:
            spec = spec_or_none(spec_text)
            if spec is not None:
                used.add(spec.scheme)
    out: list[Check] = []
    sources = {} if found is None else {s.source: s for s in found.sources}
    for scheme, (module, how) in _BACKENDS.items():
        source = sources.get(scheme)
        if source is not None:
            out.append(_source_check(scheme, source, scheme in used, rig is not None, how))
            continue
        reason = r.module_reason(module)
        if reason is None:
            out.append(Check(f"backend {scheme}", "OK", f"{module} installed"))
        elif scheme in used:
            out.append(Check(f"backend {scheme}", "FAIL", f"the config uses {scheme}:// but {reason}", how))
        else:
            out.append(Check(f"backend {scheme}", "OK", f"{module} not installed (not used by this config)"))
    return out


def _source_check(scheme: str, source: SourceReport, used: bool, have_rig: bool, how: str) -> Check:
    """A backend as `rigd devices` found it: usable (and how many devices), or unusable and why."""
    name = f"backend {scheme}"
    if source.available:
        return Check(name, "OK", f"usable ({len(source.devices)} device(s) found)")
    if used:
        return Check(name, "FAIL", f"the config uses {scheme}:// but it is unusable: {source.reason}", how)
    if have_rig:
        return Check(name, "OK", f"unusable ({source.reason}); not used by this config")
    return Check(name, "WARN", f"unusable: {source.reason}", how)


def summary_status(checks: list[Check]) -> Status:
    statuses = {c.status for c in checks}
    return "FAIL" if "FAIL" in statuses else "WARN" if "WARN" in statuses else "OK"


def checks_to_dict(checks: list[Check]) -> dict[str, object]:
    return {"status": summary_status(checks), "checks": [asdict(c) for c in checks]}
