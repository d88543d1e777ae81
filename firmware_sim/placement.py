"""Where a `sim://<world>/<name>?...` camera or event sensor sits: its world, its name, the
scene it sees, its sensor size, its clock and its unplug fault, read from the spec the same
way for both kinds, so a spec means the same whichever device it opens."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from drivers.registry import DeviceSpec
from firmware_sim.board_scene import sim_scene
from firmware_sim.cable import CABLE_PARAMS
from firmware_sim.scene import Scene
from firmware_sim.world import DeviceClock, SimWorld, UnplugParams, power_on_clock, spec_world, unplug_params
from rigd.core.devices import GROUND_TRUTH_FACT, GroundTruth
from rigd.core.errors import ConfigError

#: Spec parameters every simulated camera and event sensor takes.
PLACEMENT_PARAMS = CABLE_PARAMS | frozenset(
    {
        "offset_us",
        "drift_ppm",
        "seed",
        "width",
        "height",
        "scene",
        "unplug_at_s",
        "unplug_for_s",
        "clock_reset",
        "clock",
    }
)


@dataclass(frozen=True, slots=True)
class Placement:
    """A simulated device's place in its world, as its spec gives it."""

    world: SimWorld
    name: str
    scene: Scene
    clock: DeviceClock
    """The device clock (offset, drift), restarted from 0 after a replug with `clock_reset=1`."""
    width: int
    height: int
    seed: int
    unplug: UnplugParams | None
    spec: str


def check_ranges(spec: DeviceSpec, checks: Iterable[tuple[str, bool]]) -> None:
    """ConfigError naming the first spec parameter whose check failed."""
    for name, ok in checks:
        if not ok:
            raise ConfigError(f"device spec {spec.raw!r}: {name}={spec.params[name]!r} out of range")


def place(spec: DeviceSpec, params: Iterable[str]) -> Placement:
    """Read the placement of a spec whose own parameters are `params` (unknown ones refused)."""
    spec.check_params({*PLACEMENT_PARAMS, *params})
    name = spec.path.strip("/")
    if not name:
        raise ConfigError(f"device spec {spec.raw!r}: no device name in the path (sim://<world>/<name>)")
    width, height = spec.int_param("width", 1280), spec.int_param("height", 720)
    check_ranges(spec, (("width", 0 < width <= 65535), ("height", 0 < height <= 65535)))
    unplug = unplug_params(spec)
    seed = spec.int_param("seed", 0)
    world = spec_world(spec)
    scene = sim_scene(spec, world, seed)
    clock = DeviceClock(spec.float_param("offset_us", 0.0), spec.float_param("drift_ppm", 0.0))
    clock = power_on_clock(spec, world, name, clock)
    return Placement(world, name, scene, clock, width, height, seed, unplug, spec.raw)


def ground_truth_facts(where: Placement) -> dict[str, str]:
    """The `DeviceInfo.facts` entry with the device's exact calibration in its world (the scene
    plane's frame): the capture stores it in the take, so a sim take exports without calibrating."""
    K, R, t = where.scene.view_camera(where.name, where.width, where.height)  # noqa: N806
    truth = GroundTruth(
        world=where.world.name,
        K=K.tolist(),
        dist=[0.0] * 5,
        image_size=(where.width, where.height),
        R=R.tolist(),
        t=t.tolist(),
    )
    return {GROUND_TRUTH_FACT: truth.model_dump_json()}
