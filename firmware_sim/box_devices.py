"""Opening a simulated trigger box as a device: one box per world, on a pty (pyserial) or
behind a fake hidapi device, with the real host driver on top.

Apart from `firmware_sim.trigger_box` (the firmware) so that the firmware and its HID wrapper
(`firmware_sim.hid_box`, which builds on the firmware) do not import each other.
"""

from __future__ import annotations

import math
import threading
from typing import TYPE_CHECKING, Protocol

from firmware_sim.hid_box import SIM_HID_PID, SIM_HID_VID, FakeHidDevice, attach, box_serial
from firmware_sim.spec_params import SimTriggerParams, check_params
from firmware_sim.trigger_box import SimTriggerBox
from firmware_sim.world import SimWorld, spec_world
from rigd.core.errors import ConfigError

if TYPE_CHECKING:
    from collections.abc import Callable

    from drivers.registry import DeviceSpec
    from drivers.serial_trigger import SerialTrigger
    from drivers.trigger_link import Transport

_BOX_KEY = "trigger_box"


class OneBoxPerWorld(Protocol):
    """What the slot needs of any simulated box (the Python model or the AVR firmware)."""

    port_path: str

    @property
    def closed(self) -> bool: ...


class ClosableBox(OneBoxPerWorld, Protocol):
    def close(self) -> None: ...


class BoxSlot:
    """Per-world holder of the world's one trigger box, so a closed box can be replaced by a
    fresh one and no world gets two (their clocks would both claim to be the rig's)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.box: OneBoxPerWorld | None = None

    def check_free(self, spec: DeviceSpec, world: SimWorld) -> None:
        """Refuse a second open box, or a box in a cable follower's world (call with the lock
        held): the trigger belongs to the lead world, whose wire the cable carries."""
        if world.cable_params is not None and world.cable_params.role == "follow":
            raise ConfigError(
                f"device spec {spec.raw!r}: world {world.name!r} follows trigger cable "
                f"{world.cable_params.path}; its trigger box belongs to the lead world (cable_role=lead)"
            )
        if self.box is not None and not self.box.closed:
            raise ConfigError(
                f"device spec {spec.raw!r}: world {world.name!r} already has an open trigger box "
                f"on {self.box.port_path}"
            )


def box_slot(world: SimWorld) -> BoxSlot:
    slot = world.resource(_BOX_KEY, BoxSlot)
    assert isinstance(slot, BoxSlot)
    return slot


def find_trigger_box(world: SimWorld) -> SimTriggerBox | None:
    """The world's Python trigger box (open or last closed), for tests to reach faults and state."""
    box = box_slot(world).box
    return box if isinstance(box, SimTriggerBox) else None


def open_sim_trigger(spec: DeviceSpec) -> SerialTrigger:
    """Factory for `sim://<world>/trigger?...` (see `open_box_trigger`)."""
    check_params(spec, SimTriggerParams, "trigger box")
    return open_box_trigger(spec, spec_world(spec), SimTriggerBox)


def open_box_trigger(spec: DeviceSpec, world: SimWorld, box_class: type[SimTriggerBox]) -> SerialTrigger:
    """Start a sim box for the spec's world and open it with the real driver.

    `transport=serial` (default): the box on a pty, opened with pyserial. `transport=hid`:
    the box behind a fake hidapi device (firmware_sim.hid_box), opened with HidTransport.
    Fault switches (docs/sim-faults.md): `silent_after=N`, `garbage_after=N`, besides
    `drop_pulses`, `garbage_every` and `jitter_us`; `reply_timeout_s` / `boot_timeout_s` go to
    the host driver.
    """
    transport = spec.param("transport", "serial")
    if transport not in ("serial", "hid"):
        raise ConfigError(f"device spec {spec.raw!r}: transport={transport!r}; use serial or hid")
    # Host driver timeouts, as `serial://` and `hid://` specs take them.
    reply_timeout_s = spec.float_param("reply_timeout_s", 1.0)
    boot_timeout_s = spec.float_param("boot_timeout_s", 5.0)
    for key, value in (("reply_timeout_s", reply_timeout_s), ("boot_timeout_s", boot_timeout_s)):
        if not (0 < value < math.inf):
            raise ConfigError(f"device spec {spec.raw!r}: {key}={spec.params[key]!r} must be > 0 seconds")
    seed = spec.int_param("seed", 0)
    slot = box_slot(world)
    with slot.lock:
        slot.check_free(spec, world)
        box = box_class(
            world,
            offset_us=spec.float_param("offset_us", 0.0),
            drift_ppm=spec.float_param("drift_ppm", 0.0),
            jitter_us=spec.float_param("jitter_us", 0.0),
            drop_pulses=spec.int_list_param("drop_pulses"),
            garbage_every=spec.int_param("garbage_every", 0),
            boot_ms=spec.int_param("boot_ms", 50),
            seed=seed,
            link="socket" if transport == "hid" else "pty",
            silent_after=spec.int_param("silent_after", 0),
            garbage_after=spec.int_param("garbage_after", 0),
        )
        slot.box = box
    if transport != "hid":

        def pty_link() -> Transport:
            from firmware_sim.box_link import HandledPty

            return HandledPty(box)

        return driver_on_pty(spec, box, reply_timeout_s, boot_timeout_s, world=world, link=pty_link)

    def hid_link() -> Transport:
        from drivers.trigger_link import HidTransport

        attach(box)
        name = f"hid://{SIM_HID_VID:04x}:{SIM_HID_PID:04x}/{box_serial(box)}"
        return HidTransport(FakeHidDevice(box), name)

    return driver_on_pty(spec, box, reply_timeout_s, boot_timeout_s, world=world, link=hid_link)


def driver_on_pty(
    spec: DeviceSpec,
    box: ClosableBox,
    reply_timeout_s: float,
    boot_timeout_s: float,
    *,
    world: SimWorld,
    link: Callable[[], Transport] | None = None,
) -> SerialTrigger:
    """The real host driver on a simulated box's pty (or on the transport `link` makes); the
    box closes with it, or at once if the driver cannot open it. The driver stamps the pulse
    records with the world's host clock, as the world's cameras and sensors stamp their data."""
    from drivers.serial_trigger import SerialTrigger

    try:
        port, transport = (None, link()) if link is not None else (box.port_path, None)
        return SerialTrigger(
            port,
            transport=transport,
            spec=spec.raw,
            on_close=box.close,
            host_clock=world.host_clock,
            reply_timeout_s=reply_timeout_s,
            boot_timeout_s=boot_timeout_s,
        )
    except BaseException:
        box.close()
        raise
