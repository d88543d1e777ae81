"""Guided intrinsic calibration of one live camera of the rig.

Opens the rig's trigger and one camera (the built-in sim rig watching a moving board unless a rig
config is given), streams the newest frames into `calibration.guided.GuidedSession`, reports its
feedback frame by frame and stops when the target uncertainty is reached or time runs out. The
calibration is written with `calibration.io.write_result` whenever enough views were kept.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from calibration.boards import parse_board
from calibration.guided import Feedback, GuidedSession
from calibration.intrinsics import IntrinsicsResult
from calibration.io import write_result
from drivers.base import RgbCamera, Trigger
from drivers.registry import open_device
from rigd.app.config import CameraConfig, RigConfig, default_sim_rig
from rigd.app.workflows.calibrate import Board
from rigd.core.errors import RigdError

log = logging.getLogger(__name__)

#: World of the default sim rig: its own, so that a board scene never clashes with a sprites
#: scene another command of the same process made in the "default" world.
SIM_WORLD = "guided"
#: Frame size (width, height) of the sim rig when none is given.
SIM_RESOLUTION = (640, 360)
#: The board of the sim rig's board scene.
DEFAULT_BOARD = "chessboard:9x6:0.08"
#: Fewest kept views that make a calibration worth writing (OpenCV needs 3 for a model).
MIN_VIEWS_TO_WRITE = 3


class GuidedOptions(BaseModel):
    """One camera of the rig (`config`, else the sim rig at `resolution`, default SIM_RESOLUTION)
    and when to stop."""

    model_config = ConfigDict(frozen=True)

    camera: str
    out: Path
    config: Path | None = None
    board: Board = Field(default_factory=lambda: parse_board(DEFAULT_BOARD))
    target_sigma_px: float = 0.5
    max_seconds: float = 120.0
    still_px: float = 1.0
    min_views: int = 6
    model: str = "k1k2"
    resolution: tuple[int, int] | None = None


@dataclass(frozen=True, slots=True)
class GuidedStarted:
    """The devices are open and the session made: what is being calibrated, and the first hint."""

    camera: str
    spec: str
    frame_size: tuple[int, int]
    first_hint: str


@dataclass(frozen=True, slots=True)
class GuidedFrame:
    """One frame looked at: the session's verdict, the session itself, and the time left (s)."""

    feedback: Feedback
    session: GuidedSession
    seconds_left: float


GuidedProgress = GuidedStarted | GuidedFrame


class GuidedOutcome(BaseModel):
    """`result` is None when fewer than MIN_VIEWS_TO_WRITE views were kept (nothing written)."""

    camera: str
    done: bool
    n_views: int
    frames: int
    skipped: int
    result: IntrinsicsResult | None


def _ignore(progress: GuidedProgress) -> None:
    """The default callback: callers that show nothing need not pass one."""


def run_guided(options: GuidedOptions, progress: Callable[[GuidedProgress], None] = _ignore) -> GuidedOutcome:
    """Open the camera, run the session until done or out of time, close, write the result."""
    o = options
    cfg = RigConfig.load(o.config) if o.config is not None else guided_sim_rig(o.resolution or SIM_RESOLUTION)
    cam_cfg = _camera_config(cfg, o.camera)
    trigger, cam = _open(cfg, cam_cfg)
    try:
        session = _session(o, cam)
        shape = cam.frame_shape
        progress(GuidedStarted(o.camera, cam_cfg.spec, (int(shape[1]), int(shape[0])), session.hint_text()))
        frames, skipped = _stream(o, trigger, cam, session, progress)
    finally:
        _shutdown(trigger, cam)
    log.info("guided: %d frames looked at, %d stale frames skipped", frames, skipped)
    result = None
    if len(session.views) >= MIN_VIEWS_TO_WRITE:
        result = session.result(camera=o.camera)
        write_result(result, o.out)
    return GuidedOutcome(
        camera=o.camera,
        done=session.done,
        n_views=len(session.views),
        frames=frames,
        skipped=skipped,
        result=result,
    )


def guided_sim_rig(resolution: tuple[int, int]) -> RigConfig:
    """The built-in sim rig, in its own world, with mono frames of `resolution`."""
    return default_sim_rig(world=SIM_WORLD, resolution=resolution, pixel_format="mono8")


def _with_board_scene(spec: str) -> str:
    """Sim cameras watch the calibration board scene unless their spec picks a scene already."""
    if not spec.startswith("sim://") or "scene=" in spec:
        return spec
    return spec + ("&" if "?" in spec else "?") + "scene=board"


def _camera_config(cfg: RigConfig, camera: str) -> CameraConfig:
    for cam in cfg.cameras:
        if cam.name == camera:
            return cam.model_copy(update={"spec": _with_board_scene(cam.spec)})
    names = ", ".join(c.name for c in cfg.cameras) or "none"
    raise RigdError(f"rig {cfg.name!r} has no RGB camera {camera!r} (cameras: {names})")


def _open(cfg: RigConfig, cam_cfg: CameraConfig) -> tuple[Trigger, RgbCamera]:
    """Open and configure the trigger and the camera (order of rigd.app.capture)."""
    trigger = open_device("trigger", cfg.trigger.spec)
    try:
        trigger.configure(cfg.trigger.settings)
        cam = open_device("rgb_camera", cam_cfg.spec)
    except BaseException:
        trigger.close()
        raise
    try:
        cam.configure(cam_cfg.settings)
    except BaseException:
        cam.close()
        trigger.close()
        raise
    return trigger, cam


def _session(o: GuidedOptions, cam: RgbCamera) -> GuidedSession:
    shape = cam.frame_shape
    return GuidedSession(
        o.board,
        (int(shape[1]), int(shape[0])),
        target_sigma_px=o.target_sigma_px,
        still_px=o.still_px,
        min_views=o.min_views,
        model=o.model,
    )


def _stream(
    o: GuidedOptions,
    trigger: Trigger,
    cam: RgbCamera,
    session: GuidedSession,
    progress: Callable[[GuidedProgress], None],
) -> tuple[int, int]:
    """Offer the newest frame to the session until it is done or time runs out; (looked at, skipped)."""
    frames = skipped = 0
    cam.start()
    trigger.arm()
    trigger.start()
    t_end = time.monotonic() + o.max_seconds
    while time.monotonic() < t_end and not session.done:
        frame = cam.read_frame(0.5)
        if frame is None:
            continue
        # Live feed: always look at the newest frame; stale ones would lag the technician.
        while (newer := cam.read_frame(0.0)) is not None:
            frame, skipped = newer, skipped + 1
        trigger.read_pulses(0.0)  # nobody needs the pulse records; keep the queue short
        frames += 1
        fb = session.offer(np.asarray(frame.image), frame.t_exposure_start_us)
        progress(GuidedFrame(fb, session, t_end - time.monotonic()))
    return frames, skipped


def _shutdown(trigger: Trigger, cam: RgbCamera) -> None:
    """Stop and close both devices; one failing must not keep the others running."""
    for stop in (trigger.stop, cam.stop, cam.close, trigger.close):
        try:
            stop()
        except Exception as exc:  # noqa: BLE001  (shutdown must reach every device)
            log.error("guided: %s failed during shutdown: %s", stop.__qualname__, exc)
