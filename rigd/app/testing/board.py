"""Takes of the sim rig watching the moving calibration board (`scene=board` in every device
spec), captured through the app; their truth is in `firmware_sim.testing.board`."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from firmware_sim.testing.board import reset_world
from rigd.app.capture import CaptureResult, run_capture
from rigd.app.config import RigConfig, default_sim_rig


def board_rig(
    world: str,
    resolution: tuple[int, int],
    threshold: float | None = None,
    rate_hz: float = 30.0,
    clock: Literal["real", "virtual"] = "real",
    pixel_format: Literal["mono8", "rgb8", "bayer_rg8"] = "mono8",
) -> RigConfig:
    """The built-in sim rig with every device watching the moving board (mono8 frames unless
    `pixel_format` says otherwise).

    `clock="virtual"` runs the sim world on virtual time: the same board poses every run."""
    reset_world(world)
    cfg = default_sim_rig(
        world=world, resolution=resolution, pixel_format=pixel_format, rate_hz=rate_hz, clock=clock
    )
    data = cfg.model_dump()
    for dev in data["cameras"]:
        dev["spec"] += "&scene=board"
    for dev in data["event_sensors"]:
        dev["spec"] += "&scene=board" + (f"&threshold={threshold:g}" if threshold else "")
    return RigConfig.model_validate(data)


def capture_board_take(
    out_dir: Path,
    seconds: float,
    resolution: tuple[int, int] = (640, 360),
    threshold: float | None = None,
    world: str = "e2calib",
    clock: Literal["real", "virtual"] = "real",
    pixel_format: Literal["mono8", "rgb8", "bayer_rg8"] = "mono8",
) -> CaptureResult:
    """Capture a take of the sim rig watching the moving board (`clock="virtual"`: a
    deterministic take, the same for every run whatever the machine's load; the world is reset)."""
    rig = board_rig(world, resolution, threshold, clock=clock, pixel_format=pixel_format)
    return run_capture(rig, out_dir, seconds)
