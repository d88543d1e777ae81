"""Calibration workflows: one camera from image files, a rig from image sets or a take, and an event
sensor from a take (e2calib).

This is the one place that joins the calibration library with takes (the layering rule keeps
`calibration` free of rigd.take): it reads the views, runs the library and writes every output
asked for (OpenCV YAML or JSON, Kalibr camchain, HTML report, `/calibration/<device>` in a take).
"""

from __future__ import annotations

import glob
import logging
import re
from collections.abc import Callable
from pathlib import Path
from typing import Annotated

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, BeforeValidator, ConfigDict

from calibration.boards import BoardSpec, Detection, detect, load_image, parse_board
from calibration.e2calib import (
    METHODS,
    E2CalibResult,
    MethodResult,
    ReconstructionParams,
    StageCallback,
    calibrate_events,
    detect_in_reconstructions,
)
from calibration.errors import CalibrationError, NoBoardFoundError
from calibration.extrinsics import RigResult, calibrate_rig
from calibration.intrinsics import (
    IntrinsicsResult,
    RejectedView,
    calibrate_images,
    calibrate_intrinsics,
    detect_images,
)
from calibration.io import write_json, write_kalibr_camchain, write_opencv_yaml, write_result
from calibration.report import write_report
from rigd.core.errors import RigdError
from rigd.core.events import EventArray
from rigd.core.pixels import is_bayer, to_gray
from rigd.core.progress import ProgressCallback, ProgressUpdate, no_progress
from rigd.take.calibration import store_calibration
from rigd.take.reader import Take, open_take

log = logging.getLogger(__name__)

#: Board views of a rig: view id (trigger pulse, file number) -> device -> detection.
Views = dict[str, dict[str, Detection]]


def _as_board(value: object) -> object:
    """Board specs arrive as strings from a command line or a form."""
    return parse_board(value) if isinstance(value, str) else value


#: A board option: a BoardSpec, or a spec string parsed on validation (BoardSpecError if bad).
Board = Annotated[BoardSpec, BeforeValidator(_as_board)]


class IntrinsicsOptions(BaseModel):
    """Calibrate one camera from image files of the board."""

    model_config = ConfigDict(frozen=True)

    images: list[Path]
    board: Board
    out: Path
    camera: str = "cam0"
    model: str = "auto"
    report: Path | None = None
    into_take: Path | None = None
    #: Calibrate even when the board is not found in most images.
    allow_few_views: bool = False


class TakeSource(BaseModel):
    """Rig views from a take: the frames of one trigger pulse form one view. With `events` every
    event sensor joins the rig, from frames reconstructed at the RGB cameras' pulses."""

    model_config = ConfigDict(frozen=True)

    path: Path
    events: bool = False
    event_params: ReconstructionParams | None = None


class ImageSets(BaseModel):
    """Rig views from image files per camera, matched by the last number in the file names."""

    model_config = ConfigDict(frozen=True)

    files: dict[str, list[Path]]


class RigOptions(BaseModel):
    """Calibrate every camera of a rig and pose them in the frame of `reference`."""

    model_config = ConfigDict(frozen=True)

    board: Board
    source: TakeSource | ImageSets
    out: Path
    reference: str | None = None
    kalibr: Path | None = None
    report: Path | None = None
    model: str = "auto"
    into_take: Path | None = None


class RigCalibration(BaseModel):
    """Every device's intrinsics and the rig extrinsics they were posed with."""

    intrinsics: dict[str, IntrinsicsResult]
    rig: RigResult


class EventsOptions(BaseModel):
    """Calibrate one event sensor of a take from frames reconstructed from its events."""

    model_config = ConfigDict(frozen=True)

    take: Path
    sensor: str
    board: Board
    out: Path
    methods: list[str] = list(METHODS)
    rate_hz: float | None = None
    cutoff_hz: float = 1.0
    model: str = "k1k2"
    into_take: bool = False


class EventsCalibration(BaseModel):
    """Every method's outcome, and the best one (the one written)."""

    result: E2CalibResult
    best: MethodResult
    intrinsics: IntrinsicsResult


# --- intrinsics -----------------------------------------------------------------------------------


def run_intrinsics(options: IntrinsicsOptions, progress: ProgressCallback = no_progress) -> IntrinsicsResult:
    """Detect, select the lens model, calibrate, and write the result (and report, take entry)."""
    o = options
    result = calibrate_images(
        o.images,
        o.board,
        camera=o.camera,
        model=o.model,
        allow_few_views=o.allow_few_views,
        on_image=_image_progress(o.camera, progress),
    )
    progress(ProgressUpdate("write", f"{o.camera} -> {o.out}"))
    write_result(result, o.out)
    if o.into_take is not None:
        _store_intrinsics(o.into_take, result, f"calibrate intrinsics ({len(o.images)} images)")
    if o.report is not None:
        write_report(o.report, [result], samples={o.camera: load_image(o.images[0])})
    return result


def _image_progress(camera: str, progress: ProgressCallback) -> Callable[[int, int], None]:
    """Images searched for the board, as workflow progress; the lens-model fit follows."""

    def on_image(done: int, total: int) -> None:
        progress(ProgressUpdate("detect", camera, done, total, "images searched for the board"))
        if done == total:
            progress(ProgressUpdate("calibrate", f"{camera}: choosing and fitting the lens model"))

    return on_image


def _store_intrinsics(take: Path, result: IntrinsicsResult, source: str, device: str | None = None) -> None:
    summary = result.summary()
    if device is not None:
        summary["camera"] = device
    store_calibration(take, device or result.camera, intrinsics=summary, source=source)


# --- rig ------------------------------------------------------------------------------------------


def glob_images(pattern: str) -> list[Path]:
    """Image files of one camera, in name order (the order views fall back on without numbers)."""
    return [Path(p) for p in sorted(glob.glob(pattern))]


def run_rig(options: RigOptions, progress: ProgressCallback = no_progress) -> RigCalibration:
    """Intrinsics of every device, then all poses in one rig frame from simultaneous board views."""
    o = options
    if isinstance(o.source, TakeSource):
        intr, views = take_views(o.board, o.source, o.model, progress)
    else:
        intr, views = image_set_views(o.board, o.source.files, o.model, progress)
    progress(ProgressUpdate("calibrate", f"rig: {len(intr)} devices, {len(views)} views"))
    rig = calibrate_rig(intr, views, o.board, reference=o.reference)
    _write_rig(o, intr, rig, progress)
    return RigCalibration(intrinsics=intr, rig=rig)


def _write_rig(
    o: RigOptions, intr: dict[str, IntrinsicsResult], rig: RigResult, progress: ProgressCallback
) -> None:
    progress(ProgressUpdate("write", f"rig -> {o.out}"))
    if o.out.suffix.lower() == ".json":
        write_json(rig, o.out)
    else:
        write_opencv_yaml(intr, o.out, rig)
    if o.kalibr is not None:
        write_kalibr_camchain(intr, o.kalibr, rig)
    if o.into_take is not None:
        for pose in rig.cameras:
            store_calibration(
                o.into_take,
                pose.camera,
                intrinsics=intr[pose.camera].summary(),
                pose=pose.model_dump(),
                source=f"calibrate rig (reference {rig.reference})",
            )
    if o.report is not None:
        write_report(o.report, list(intr.values()), rig)


def _file_view_key(path: Path, index: int) -> str:
    """View id of an image file: the last number in its stem (left07.png -> 07), else its index."""
    nums = re.findall(r"\d+", path.stem)
    return nums[-1].lstrip("0") or "0" if nums else str(index)


def image_set_views(
    board: BoardSpec, sets: dict[str, list[Path]], model: str, progress: ProgressCallback = no_progress
) -> tuple[dict[str, IntrinsicsResult], Views]:
    """Intrinsics per camera and the views they share, from image files."""
    intr: dict[str, IntrinsicsResult] = {}
    views: Views = {}
    for cam, files in sets.items():
        dets, rej, warn = detect_images(files, board, _image_progress(cam, progress))
        keys = {f.name: _file_view_key(f, i) for i, f in enumerate(files)}
        intr[cam] = calibrate_intrinsics(dets, board, camera=cam, model=model, rejected=rej, warnings=warn)
        for d in dets:
            views.setdefault(keys[d.name], {})[cam] = d
    return intr, views


def _pulse_key(pulse_index: int, index: int) -> str:
    """View id of a frame: its trigger pulse, else (no pulse) its index."""
    return str(pulse_index if pulse_index >= 0 else index)


def take_views(
    board: BoardSpec, source: TakeSource, model: str, progress: ProgressCallback = no_progress
) -> tuple[dict[str, IntrinsicsResult], Views]:
    """Intrinsics per device and the views they share, from the frames (and events) of a take.

    With `source.events`, an event view is reconstructed (`calibration.e2calib`, accurate method)
    at the mid-exposure instant of each RGB frame of the first camera and labelled with that
    frame's pulse, so an event view and the RGB views of one pulse show the same board pose and
    the joint refinement ties the sensor into the rig frame.
    """
    intr: dict[str, IntrinsicsResult] = {}
    views: Views = {}
    with open_take(source.path) as take:
        for cam in take.cameras:
            found, result = _camera_views(take, cam, board, model, progress)
            _merge_views(views, cam, found)
            if result is not None:
                intr[cam] = result
        if source.events and take.event_sensors:
            keys, times = _pulse_instants(take)
            for sensor in take.event_sensors:
                found, result = _event_sensor_views(take, sensor, board, model, keys, times, source, progress)
                _merge_views(views, sensor, found)
                if result is not None:
                    intr[sensor] = result
    return intr, views


def _merge_views(views: Views, device: str, found: dict[str, Detection]) -> None:
    for key, d in found.items():
        views.setdefault(key, {})[device] = d


def _camera_views(
    take: Take, cam: str, board: BoardSpec, model: str, progress: ProgressCallback = no_progress
) -> tuple[dict[str, Detection], IntrinsicsResult | None]:
    """The board in every frame of one camera, keyed by pulse; None when it is in none of them."""
    series = take.camera(cam, demosaic=False)
    bayer = is_bayer(series.pixel_format)
    dets: list[Detection] = []
    found: dict[str, Detection] = {}
    rejected: list[RejectedView] = []
    for i in range(len(series)):
        progress(ProgressUpdate("detect", cam, i, len(series), "frames searched for the board"))
        frame = series[i]
        key = _pulse_key(frame.pulse_index, i)
        # A Bayer camera's board is found in the demosaiced gray image.
        image = to_gray(frame.image, series.pixel_format) if bayer else frame.image
        d = detect(np.asarray(image), board, name=f"{cam}#{key}")
        if d is None:
            rejected.append(RejectedView(name=f"{cam}#{key}", reason=f"board {board} not found"))
            continue
        dets.append(d)
        found[key] = d
    if not dets:
        log.warning("take %s: board not found in any frame of camera %s", take.path, cam)
        return found, None
    progress(ProgressUpdate("calibrate", f"{cam}: fitting the lens model to {len(dets)} views"))
    return found, calibrate_intrinsics(dets, board, camera=cam, model=model, rejected=rejected)


def _pulse_instants(take: Take) -> tuple[list[str], NDArray[np.int64]]:
    """View keys and mid-exposure times (take clock, us) of the first camera's frames."""
    if not take.cameras or not len(take.camera(take.cameras[0])):
        raise RigdError(
            f"{take.path}: --events needs RGB frames: their trigger pulses are the instants "
            "the event views are reconstructed at"
        )
    series = take.camera(take.cameras[0])
    frames = [series[i] for i in range(len(series))]
    keys = [_pulse_key(f.pulse_index, i) for i, f in enumerate(frames)]
    half = np.asarray([f.exposure_us // 2 for f in frames], np.int64)
    return keys, np.asarray(series.timestamps_us, np.int64) + half


def _event_sensor_views(
    take: Take,
    sensor: str,
    board: BoardSpec,
    model: str,
    keys: list[str],
    times: NDArray[np.int64],
    source: TakeSource,
    progress: ProgressCallback = no_progress,
) -> tuple[dict[str, Detection], IntrinsicsResult | None]:
    """The board in frames of one sensor reconstructed at the pulse instants, keyed by pulse; None
    when the sensor has no events or the board is in no reconstruction (it leaves the rig)."""
    series = take.sensor(sensor)
    ev = series.events()
    if len(ev) == 0:
        log.warning("take %s: event sensor %s has no events; left out of the rig", take.path, sensor)
        return {}, None
    names = [f"{sensor}#{k}" for k in keys]
    rec = detect_in_reconstructions(
        ev,
        series.geometry,
        times,
        board,
        params=source.event_params,
        names=names,
        sensor=sensor,
        on_progress=stage_progress(sensor, progress, len(keys)),
    )
    if not rec.detections:
        log.warning("take %s: board not found in any reconstruction of %s", take.path, sensor)
        return {}, None
    found = {k: d for k, name in zip(keys, names, strict=True) if (d := rec.detections.get(name)) is not None}
    result = calibrate_intrinsics(
        list(rec.detections.values()), board, camera=sensor, model=model, rejected=rec.rejected
    )
    log.info(
        "take %s: %s: board in %d/%d reconstructions, RMS %.3f px",
        take.path,
        sensor,
        len(rec.detections),
        len(keys),
        result.rms_px,
    )
    return found, result


# --- event sensor (e2calib) -----------------------------------------------------------------------


def event_times(take_path: Path, sensor: str, rate_hz: float | None = None) -> NDArray[np.int64]:
    """Times (take clock, us) to reconstruct a sensor's frames at: every `rate_hz` over its event
    span, else the cameras' mid-exposure instants (the pulses the RGB frames show, so event and
    RGB views of one pulse see the same board pose), else the sensor's rising trigger edges."""
    with open_take(take_path) as take:
        if sensor not in take.event_sensors:
            raise RigdError(f"{take_path}: no event sensor {sensor!r} (has {take.event_sensors})")
        if rate_hz is not None:
            if rate_hz <= 0:
                raise RigdError(f"--rate must be > 0 Hz, got {rate_hz}")
            span = take.sensor(sensor).span
            if span is None:
                raise RigdError(f"{take_path}: event sensor {sensor!r} has no events")
            return np.arange(span[0], span[1], 1e6 / rate_hz).astype(np.int64)
        if take.cameras:
            cam = take.camera(take.cameras[0])
            if len(cam):
                return np.asarray(cam.timestamps_us + cam[0].exposure_us // 2, np.int64)
        trig = take.sensor(sensor).triggers
        return np.asarray(trig.t[trig.p == 1], np.int64)


#: Frames reconstructed over the take to check that it shows the board at all.
_PROBE_FRAMES = 8


def _check_board_seen(
    take_path: Path,
    sensor: str,
    events: EventArray,
    size: tuple[int, int],
    times: NDArray[np.int64],
    board: BoardSpec,
    methods: list[str],
    params: ReconstructionParams | None,
) -> None:
    """NoBoardFoundError (saying how to record a board take) when no method finds the board in
    any of a few frames spread over the take."""
    if len(events) == 0 or times.size == 0:
        return  # calibrate_events says what is missing
    idx = np.unique(np.linspace(0, times.size - 1, min(_PROBE_FRAMES, times.size)).round().astype(np.int64))
    probe = times[idx]
    for method in [m for m in methods if m in METHODS]:
        found = detect_in_reconstructions(events, size, probe, board, method, params, sensor=sensor)
        if found.detections:
            return
    raise NoBoardFoundError(
        f"{take_path}: sensor {sensor}: board {board} not found in {probe.size} frames reconstructed over "
        f"the take ({', '.join(methods)}); record a take of the board (on the sim: scene=board, "
        f"e.g. sim://W/{sensor}?scene=board)"
    )


#: What each e2calib stage counts, for a progress display.
_STAGE_UNITS = {"reconstruct": "", "detect": "frames searched for the board", "calibrate": ""}


def stage_progress(sensor: str, progress: ProgressCallback, count: int) -> StageCallback:
    """A `calibration.e2calib` stage callback that reports as workflow progress (`count` frames
    are reconstructed per method)."""

    def on_stage(stage: str, method: str, done: int | None, total: int | None) -> None:
        what = {
            "reconstruct": f"{sensor}, {method}: reconstructing {count} frames from the events",
            "detect": f"{sensor}, {method}",
            "calibrate": f"{sensor}, {method}: fitting the lens model",
        }.get(stage, f"{sensor}, {method}")
        progress(ProgressUpdate(stage, what, done, total, _STAGE_UNITS.get(stage, "")))

    return on_stage


def calibrate_take_events(
    take_path: Path,
    sensor: str,
    board: BoardSpec,
    methods: list[str],
    rate_hz: float | None = None,
    params: ReconstructionParams | None = None,
    model: str = "k1k2",
    progress: ProgressCallback = no_progress,
) -> E2CalibResult:
    """e2calib on one sensor of a take (see calibration.e2calib), at `event_times`.

    A few frames spread over the take are checked first, so a take without a board fails at once.
    """
    times = event_times(take_path, sensor, rate_hz)
    progress(ProgressUpdate("read", f"{sensor}: events of {take_path.name}"))
    with open_take(take_path) as take:
        series = take.sensor(sensor)
        events, size = series.events(), series.geometry
    progress(ProgressUpdate("check", f"{sensor}: is the board in a few frames over the take?"))
    _check_board_seen(take_path, sensor, events, size, times, board, methods, params)
    return calibrate_events(
        events,
        size,
        times,
        board,
        sensor=sensor,
        methods=methods,
        params=params,
        model=model,
        on_progress=stage_progress(sensor, progress, times.size),
    )


def run_events(options: EventsOptions, progress: ProgressCallback = no_progress) -> EventsCalibration:
    """Every reconstruction method on one sensor; the one with the lowest RMS is written."""
    o = options
    res = calibrate_take_events(
        o.take,
        o.sensor,
        o.board,
        o.methods,
        o.rate_hz,
        ReconstructionParams(cutoff_hz=o.cutoff_hz),
        o.model,
        progress,
    )
    best = res.best()
    if best.intrinsics is None:  # best() only returns a calibrated method
        raise CalibrationError(f"sensor {o.sensor}: method {best.method} has no calibration")
    progress(ProgressUpdate("write", f"{o.sensor} ({best.method}) -> {o.out}"))
    write_result(best.intrinsics, o.out)
    if o.into_take:
        _store_intrinsics(o.take, best.intrinsics, f"calibrate events ({best.method})", device=o.sensor)
    return EventsCalibration(result=res, best=best, intrinsics=best.intrinsics)
