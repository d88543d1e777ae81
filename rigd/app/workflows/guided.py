"""Guided intrinsic calibration of one live camera of the rig.

Opens the rig's trigger and one camera (the built-in sim rig watching a moving board unless a rig
config is given), streams the newest frames into `calibration.guided.GuidedSession`, reports its
feedback frame by frame and stops when the target uncertainty is reached or time runs out. The
calibration is written with `calibration.io.write_result` whenever enough views were kept.
"""

from __future__ import annotations

import logging
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from calibration.boards import parse_board
from calibration.guided import SIGMA_NAMES, Feedback, GuidedSession
from calibration.intrinsics import RECOMMENDED_VIEWS, IntrinsicsResult
from calibration.io import write_result
from calibration.report import write_report
from rigd.app.config import CameraConfig, EventSensorConfig, RigConfig, default_sim_rig
from rigd.app.workflows.guided_feeds import ImageFeed, open_camera_feed, open_event_feed
from rigd.core.errors import RigdError
from rigd.products.calibrate import Board

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
    sim_clock: Literal["real", "virtual"] = "real"
    """The built-in sim rig's clock (ignored with `config`): "virtual" gives the same session
    on any machine, however loaded (see SessionBudget)."""

    @property
    def out_path(self) -> Path:
        return self.out if self.out is not None else Path(f"{self.camera}.yaml")

    @property
    def done_views(self) -> int:
        """Fewest views the written calibration must use to be done: the report's recommendation
        (calibration.intrinsics.RECOMMENDED_VIEWS), or `min_views` when that asks for more."""
        return max(self.min_views, RECOMMENDED_VIEWS)


@dataclass(frozen=True, slots=True)
class GuidedStarted:
    """The devices are open and the session made: what is being calibrated, and the first hint."""

    camera: str
    spec: str
    frame_size: tuple[int, int]
    first_hint: str


@dataclass(frozen=True, slots=True)
class GuidedFrame:
    """One frame looked at: the session's verdict, the session itself, and the time left (s, >= 0)."""

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
        while not run.budget.spent and not run.session.done:
            looked = run.step()
            if looked is not None:
                progress(GuidedFrame(looked[0], run.session, run.budget.left()))
    finally:
        run.close()
    return run.finish()


class SessionBudget:
    """The session's time left: wall seconds on a rig in real time; on a sim rig on virtual time,
    seconds of the camera's own time looked at (frame timestamps).

    Why two: a live rig gives its frames in wall time and a technician waits in wall time. A sim
    on virtual time runs as fast as the host allows, so a wall-clock limit would make the session
    (and a test of it) depend on how loaded the machine is; the camera's time does not. A sim that
    stops sending frames for STALL_S wall seconds ends the session all the same.
    """

    #: Wall seconds without a frame after which a session on virtual time gives up.
    STALL_S = 30.0

    def __init__(
        self, seconds: float, *, device_time: bool, wall: Callable[[], float] = time.monotonic
    ) -> None:
        self.seconds = seconds
        self.device_time = device_time
        self._wall = wall
        self._wall_start = self._last_frame_wall = wall()
        self._t_first_us: int | None = None
        self._t_last_us: int | None = None

    def saw(self, t_us: int) -> None:
        """A frame of camera time `t_us` was looked at."""
        if self._t_first_us is None:
            self._t_first_us = t_us
        self._t_last_us = t_us
        self._last_frame_wall = self._wall()

    def left(self) -> float:
        """Seconds left (>= 0)."""
        if not self.device_time:
            return max(0.0, self.seconds - (self._wall() - self._wall_start))
        if self._t_first_us is None or self._t_last_us is None:
            return self.seconds
        return max(0.0, self.seconds - (self._t_last_us - self._t_first_us) / 1e6)

    @property
    def stalled(self) -> bool:
        """On virtual time: no frame for STALL_S wall seconds."""
        return self.device_time and self._wall() - self._last_frame_wall >= self.STALL_S

    @property
    def spent(self) -> bool:
        return self.left() <= 0.0 or self.stalled


class GuidedRun:
    """A guided session on open devices, driven one frame at a time (the CLI loops over `step`,
    the web console runs it on a worker and lets the technician drop views and finish).

    `options.camera` names an RGB camera or an event sensor of the rig; an event sensor is seen
    through images reconstructed from its events (rigd.app.workflows.guided_feeds)."""

    def __init__(self, options: GuidedOptions, rig: RigConfig | None = None) -> None:
        self.options = options
        o = options
        if rig is None:
            if o.config:
                rig = RigConfig.load(o.config)
            else:
                rig = guided_sim_rig(o.resolution or SIM_RESOLUTION, o.sim_clock)
        self.rig = rig
        self.device_cfg, self._open_feed = _device_config(rig, o.camera)
        self.virtual_time = rig.on_virtual_time()
        self.budget = SessionBudget(o.max_seconds, device_time=self.virtual_time)
        self._feed: ImageFeed | None = None
        self._session: GuidedSession | None = None
        self.frames = 0

    @property
    def skipped(self) -> int:
        return 0 if self._feed is None else self._feed.skipped

    @property
    def session(self) -> GuidedSession:
        if self._session is None:
            raise RigdError("the guided session is not open")
        return self._session

    def open(self) -> GuidedStarted:
        """Open and start the trigger and the device; make the session."""
        dev, open_feed = self.device_cfg, self._open_feed
        feed = open_feed(self.rig, not self.virtual_time)
        try:
            w, h = feed.size
            self._session = _session(self.options, (h, w), feed.exposure_us, feed.still_px)
        except BaseException:
            feed.close()
            raise
        self._feed = feed
        return GuidedStarted(self.options.camera, dev.spec, feed.size, self.session.hint_text())

    def step(self, timeout_s: float = 0.5) -> tuple[Feedback, NDArray[np.uint8]] | None:
        """Offer the newest image to the session; None when none came within `timeout_s`."""
        if self._feed is None:
            raise RigdError("the guided session's devices are closed")
        got = self._feed.read(timeout_s)
        if got is None:
            return None
        image, t_us = got
        self.frames += 1
        feedback = self.session.offer(image, t_us)
        self.budget.saw(t_us)
        return feedback, image

    def close(self) -> None:
        """Stop and close the devices (idempotent)."""
        if self._feed is not None:
            self._feed.close()
            self._feed = None

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


def verdict(outcome: GuidedOutcome, target_sigma_px: float, done_views: int) -> tuple[bool, str]:
    """(target reached, the verdict in words), judged on the calibration that was written, by the
    session's own stop rule: all four std devs at or below the target, from at least `done_views`
    views the fit used (GuidedOptions.done_views; outliers it rejected do not count)."""
    result = outcome.result
    if result is None:
        return False, f"only {outcome.n_views} view(s) captured; nothing written"
    sig = {k: result.std_devs[k] for k in SIGMA_NAMES}
    above = [f"{k} {v:.3f}" for k, v in sig.items() if not v <= target_sigma_px]
    used = len(result.views)
    if not above and used >= done_views:
        return True, "target reached"
    if not above:
        return False, (
            f"stopped at {used} usable views of the {done_views} needed: the std devs are below the "
            f"{target_sigma_px:g} px target, but from fewer views than the report recommends"
        )
    return False, f"stopped before the {target_sigma_px:g} px target ({', '.join(above)} px above it)"


def views_text(outcome: GuidedOutcome) -> str:
    """How many views were kept and how many of them the written fit used, one way everywhere."""
    result = outcome.result
    if result is None:
        return f"{outcome.n_views} views kept"
    used = len(result.views)
    rejected = outcome.n_views - used
    return f"{used} views" + (
        f" ({outcome.n_views} kept, {rejected} rejected as outliers)" if rejected else ""
    )


def guided_sim_rig(resolution: tuple[int, int], clock: Literal["real", "virtual"] = "real") -> RigConfig:
    """The built-in sim rig, in its own world (one per clock: a world runs on one), with mono
    frames of `resolution`."""
    # On virtual time a world of its own per session: time starts at 0 in a fresh world, so
    # every session in a process is the same one (a process keeps its worlds and their truth logs).
    world = f"{SIM_WORLD}-virtual-{uuid.uuid4().hex[:8]}" if clock == "virtual" else SIM_WORLD
    return default_sim_rig(world=world, resolution=resolution, pixel_format="mono8", clock=clock)


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


#: Opens a device's live feed: (rig, newest frame only) -> the started feed.
FeedOpener = Callable[[RigConfig, bool], ImageFeed]


def _camera_feed(cam: CameraConfig, rig: RigConfig, newest_only: bool) -> ImageFeed:
    return open_camera_feed(rig, cam, newest_only=newest_only)


def _event_feed(sensor: EventSensorConfig, rig: RigConfig, newest_only: bool) -> ImageFeed:
    return open_event_feed(rig, sensor)  # every event counts: there is no newer image to skip to


def _device_config(cfg: RigConfig, name: str) -> tuple[CameraConfig | EventSensorConfig, FeedOpener]:
    """The camera or event sensor called `name`, watching the board scene on the sim, and how
    its live feed opens (a camera's frames, or images reconstructed from a sensor's events)."""
    for cam in cfg.cameras:
        if cam.name == name:
            on_board = cam.model_copy(update={"spec": _with_board_scene(cam.spec)})
            return on_board, partial(_camera_feed, on_board)
    for sensor in cfg.event_sensors:
        if sensor.name == name:
            on_board_ev = sensor.model_copy(update={"spec": _with_board_scene(sensor.spec)})
            return on_board_ev, partial(_event_feed, on_board_ev)
    names = ", ".join(c.name for c in cfg.cameras) or "none"
    sensors = ", ".join(c.name for c in cfg.event_sensors) or "none"
    raise RigdError(
        f"rig {cfg.name!r} has no RGB camera {name!r} nor an event sensor of that name "
        f"(cameras: {names}; event sensors: {sensors})"
    )


def _session(
    o: GuidedOptions, shape: tuple[int, ...], exposure_us: float | None, still_px: float | None = None
) -> GuidedSession:
    return GuidedSession(
        o.board,
        (int(shape[1]), int(shape[0])),
        target_sigma_px=o.target_sigma_px,
        still_px=o.still_px if still_px is None else still_px,
        min_views=o.min_views,
        done_views=o.done_views,
        model=o.model,
        exposure_us=exposure_us,
    )
