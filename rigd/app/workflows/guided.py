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
from calibration.guided import SIGMA_NAMES, Feedback, GuidedSession
from calibration.intrinsics import IntrinsicsResult
from calibration.io import write_result
from calibration.report import write_report
from drivers.base import RgbCamera, Trigger
from drivers.registry import open_device
from rigd.app.config import CameraConfig, RigConfig, default_sim_rig
from rigd.app.workflows.calibrate import Board
from rigd.core.errors import RigdError
from rigd.core.frames import Frame

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
    and when to stop. `still_px` bounds the board's smear during one exposure (see
    calibration.guided); `out` defaults to `<camera>.yaml` in the working directory."""

    model_config = ConfigDict(frozen=True)

    camera: str
    out: Path | None = None
    report: Path | None = None
    config: Path | None = None
    board: Board = Field(default_factory=lambda: parse_board(DEFAULT_BOARD))
    target_sigma_px: float = 0.5
    max_seconds: float = 120.0
    still_px: float = 1.0
    min_views: int = 6
    model: str = "k1k2"
    resolution: tuple[int, int] | None = None

    @property
    def out_path(self) -> Path:
        return self.out if self.out is not None else Path(f"{self.camera}.yaml")


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


def run_guided(
    options: GuidedOptions, progress: Callable[[GuidedProgress], None] = _ignore, rig: RigConfig | None = None
) -> GuidedOutcome:
    """Open the camera, run the session until done or out of time, close, write the result.

    `rig`: the rig config to use instead of `options.config` (the daemon's own, for the console)."""
    run = GuidedRun(options, rig)
    started = run.open()
    try:
        progress(started)
        t_end = time.monotonic() + options.max_seconds
        while time.monotonic() < t_end and not run.session.done:
            looked = run.step()
            if looked is not None:
                progress(GuidedFrame(looked[0], run.session, t_end - time.monotonic()))
    finally:
        run.close()
    return run.finish()


class GuidedRun:
    """A guided session on open devices, driven one frame at a time (the CLI loops over `step`,
    the web console runs it on a worker and lets the technician drop views and finish)."""

    def __init__(self, options: GuidedOptions, rig: RigConfig | None = None) -> None:
        self.options = options
        o = options
        if rig is None:
            rig = RigConfig.load(o.config) if o.config else guided_sim_rig(o.resolution or SIM_RESOLUTION)
        self.rig = rig
        self.cam_cfg = _camera_config(rig, o.camera)
        self._devices: tuple[Trigger, RgbCamera] | None = None
        self._session: GuidedSession | None = None
        self.frames = 0
        self.skipped = 0

    @property
    def session(self) -> GuidedSession:
        if self._session is None:
            raise RigdError("the guided session is not open")
        return self._session

    def open(self) -> GuidedStarted:
        """Open and start the trigger and the camera; make the session."""
        trigger, cam = _open(self.rig, self.cam_cfg)
        try:
            self._session = _session(self.options, cam, self.cam_cfg.settings.exposure_us)
            cam.start()
            trigger.arm()
            trigger.start()
        except BaseException:
            _shutdown(trigger, cam)
            raise
        self._devices = (trigger, cam)
        shape = cam.frame_shape
        return GuidedStarted(
            self.options.camera, self.cam_cfg.spec, (int(shape[1]), int(shape[0])), self._session.hint_text()
        )

    def step(self, timeout_s: float = 0.5) -> tuple[Feedback, Frame] | None:
        """Offer the newest frame to the session; None when no frame came within `timeout_s`."""
        if self._devices is None:
            raise RigdError("the guided session's devices are closed")
        trigger, cam = self._devices
        frame = cam.read_frame(timeout_s)
        if frame is None:
            return None
        # Live feed: always look at the newest frame; stale ones would lag the technician.
        while (newer := cam.read_frame(0.0)) is not None:
            frame, self.skipped = newer, self.skipped + 1
        trigger.read_pulses(0.0)  # nobody needs the pulse records; keep the queue short
        self.frames += 1
        return self.session.offer(np.asarray(frame.image), frame.t_exposure_start_us), frame

    def close(self) -> None:
        """Stop and close the devices (idempotent)."""
        if self._devices is not None:
            _shutdown(*self._devices)
            self._devices = None

    def finish(self) -> GuidedOutcome:
        """Close the devices; write the calibration (and report) when enough views were kept."""
        self.close()
        o, session = self.options, self.session
        log.info("guided: %d frames looked at, %d stale frames skipped", self.frames, self.skipped)
        result = None
        if len(session.views) >= MIN_VIEWS_TO_WRITE:
            result = session.result(camera=o.camera)
            write_result(result, o.out_path)
            if o.report is not None:
                write_report(o.report, [result])
        return GuidedOutcome(
            camera=o.camera,
            done=session.done,
            n_views=len(session.views),
            frames=self.frames,
            skipped=self.skipped,
            result=result,
        )


def verdict(outcome: GuidedOutcome, target_sigma_px: float, min_views: int) -> tuple[bool, str]:
    """(target reached, the verdict in words), judged on the calibration that was written.

    Why not `outcome.done` alone: the session judges the target on its running fast fit, and only
    from `min_views` views on, while the written result is the full calibration of the views
    kept; so "time ran out before the target" could sit next to four std devs below it."""
    result = outcome.result
    if result is None:
        return False, f"only {outcome.n_views} view(s) captured; nothing written"
    sig = {k: result.std_devs[k] for k in SIGMA_NAMES}
    above = [f"{k} {v:.3f}" for k, v in sig.items() if not v <= target_sigma_px]
    if not above and outcome.n_views >= min_views:
        return True, "target reached"
    if not above:
        return False, (
            f"time ran out at {outcome.n_views} of {min_views} views: the std devs are below the "
            f"{target_sigma_px:g} px target, but from fewer views than asked for"
        )
    return False, f"time ran out before the {target_sigma_px:g} px target ({', '.join(above)} px above it)"


def guided_sim_rig(resolution: tuple[int, int]) -> RigConfig:
    """The built-in sim rig, in its own world, with mono frames of `resolution`."""
    return default_sim_rig(world=SIM_WORLD, resolution=resolution, pixel_format="mono8")


def own_sim_world(rig: RigConfig, suffix: str = "-guided") -> RigConfig:
    """The rig with its sim devices moved to a world of their own (`<world><suffix>`).

    Why: a sim world holds one scene; the daemon's takes made the sprites scene in the rig's
    world, and the board scene cannot join it. Real devices are left as they are."""

    def moved(spec: str) -> str:
        if not spec.startswith("sim://"):
            return spec
        world, sep, rest = spec.removeprefix("sim://").partition("/")
        return f"sim://{world}{suffix}{sep}{rest}"

    data = rig.model_dump(mode="json")
    data["trigger"]["spec"] = moved(data["trigger"]["spec"])
    for dev in [*data["cameras"], *data["event_sensors"]]:
        dev["spec"] = moved(dev["spec"])
    return RigConfig.from_data(data)


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


def _session(o: GuidedOptions, cam: RgbCamera, exposure_us: float | None) -> GuidedSession:
    shape = cam.frame_shape
    return GuidedSession(
        o.board,
        (int(shape[1]), int(shape[0])),
        target_sigma_px=o.target_sigma_px,
        still_px=o.still_px,
        min_views=o.min_views,
        model=o.model,
        exposure_us=exposure_us,
    )


def _shutdown(trigger: Trigger, cam: RgbCamera) -> None:
    """Stop and close both devices; one failing must not keep the others running."""
    for stop in (trigger.stop, cam.stop, cam.close, trigger.close):
        try:
            stop()
        except Exception as exc:  # noqa: BLE001  (shutdown must reach every device)
            log.error("guided: %s failed during shutdown: %s", stop.__qualname__, exc)
