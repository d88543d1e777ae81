"""`avr://WORLD/trigger?elf=PATH&mcu=atmega328p`: the trigger-box firmware under simavr as a
world's trigger, opened with the real host driver on the harness's pty."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field

from firmware_sim.avr.box import AvrTriggerBox
from firmware_sim.box_devices import box_slot, driver_on_pty
from firmware_sim.spec_params import CableSpecParams, Clock, Seed, check_params
from firmware_sim.world import SimWorld, spec_world
from rigd.core.errors import ConfigError

if TYPE_CHECKING:
    from drivers.registry import DeviceSpec
    from drivers.serial_trigger import SerialTrigger

#: Where `make -C firmware/trigger_box` puts the images, in a source checkout.
FIRMWARE_BUILD = Path(__file__).resolve().parents[2] / "firmware" / "trigger_box" / "build"
MCUS = ("atmega328p", "atmega2560")


class AvrTriggerParams(CableSpecParams):
    elf: str | None = None
    mcu: Literal["atmega328p", "atmega2560"] | None = None
    seed: Seed | None = None
    clock: Clock | None = None
    reply_timeout_s: Annotated[float, Field(gt=0, le=60)] | None = None
    boot_timeout_s: Annotated[float, Field(gt=0, le=600)] | None = None


def default_elf(mcu: str) -> Path:
    return FIRMWARE_BUILD / f"trigger_box_{mcu}.elf"


def resolve_elf(spec: DeviceSpec, params: AvrTriggerParams) -> tuple[Path, str]:
    """The image to run and its chip: `elf=` (a path) or the built image for `mcu=`."""
    mcu: str
    if params.elf:
        elf = Path(params.elf).expanduser()
        guessed = [m for m in MCUS if m in elf.name]
        mcu = params.mcu or (guessed[0] if guessed else "atmega328p")
    else:
        mcu = params.mcu or "atmega328p"
        elf = default_elf(mcu)
    if not elf.is_file():
        hint = " (build it: make -C firmware/trigger_box)" if elf.parent == FIRMWARE_BUILD else ""
        raise ConfigError(f"device spec {spec.raw!r}: firmware image {str(elf)!r} not found{hint}")
    return elf, mcu


def find_avr_box(world: SimWorld) -> AvrTriggerBox | None:
    """The world's AVR trigger box (open or last closed), for tests."""
    box = box_slot(world).box
    return box if isinstance(box, AvrTriggerBox) else None


def open_avr_trigger(spec: DeviceSpec) -> SerialTrigger:
    """Start the firmware for the spec's world and open it with the real driver."""
    params = check_params(spec, AvrTriggerParams, "AVR trigger box")
    elf, mcu = resolve_elf(spec, params)
    reply_timeout_s = params.reply_timeout_s or 1.0
    boot_timeout_s = params.boot_timeout_s or 5.0
    world = spec_world(spec)
    slot = box_slot(world)
    with slot.lock:
        slot.check_free(spec, world)
        box = AvrTriggerBox(world, elf, mcu=mcu)
        slot.box = box
    return driver_on_pty(spec, box, reply_timeout_s, boot_timeout_s, world=world)
