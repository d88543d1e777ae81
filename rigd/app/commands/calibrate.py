"""`rigd calibrate ...`: intrinsics from image files, rig extrinsics from image sets or a take.

This module is the one place that joins the calibration library with takes (the layering rule
keeps `calibration` free of rigd.take). Register with `app.add_typer(calibrate_app, name="calibrate")`.
Exit code 2 on a RigdError, with the message on stderr; `--json` prints the result on stdout.
"""

from __future__ import annotations

import glob
import json
import logging
import re
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.console import Console

from calibration.boards import BoardSpec, Detection, detect, load_image, parse_board
from calibration.e2calib import (
    METHODS,
    E2CalibResult,
    ReconstructionParams,
    calibrate_events,
    detect_in_reconstructions,
)
from calibration.extrinsics import RigResult, calibrate_rig
from calibration.intrinsics import (
    IntrinsicsResult,
    RejectedView,
    calibrate_images,
    calibrate_intrinsics,
    detect_images,
)
from calibration.io import dumps_summary, write_json, write_kalibr_camchain, write_opencv_yaml, write_result
from calibration.report import write_report
from rigd.core.errors import RigdError
from rigd.take.calibration import store_calibration

log = logging.getLogger(__name__)

calibrate_app = typer.Typer(
    help="Calibrate cameras: intrinsics, event-sensor intrinsics (e2calib), rig extrinsics.",
    no_args_is_help=True,
)
_err = Console(stderr=True)

BoardOpt = Annotated[str, typer.Option("--board", "-b", help="Board spec, e.g. chessboard:9x6:0.025.")]
OutOpt = Annotated[Path, typer.Option("--out", "-o", help="Output file: .yaml/.yml/.xml (OpenCV) or .json.")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print the result as JSON on stdout.")]
ReportOpt = Annotated[Path | None, typer.Option("--report", help="Write an HTML report here.")]
ModelOpt = Annotated[
    str, typer.Option("--model", help="Lens model, or 'auto' for cross-validated selection.")
]


def _fail(exc: Exception) -> typer.Exit:
    _err.print(f"[bold red]error:[/] {exc}")
    return typer.Exit(code=2)


def _warn(result: IntrinsicsResult | RigResult) -> None:
    for w in result.warnings:
        _err.print(f"[yellow]warning:[/] {w}")
    for r in getattr(result, "rejected", []):
        _err.print(f"[yellow]rejected:[/] {r.name}: {r.reason}")


IntoTakeOpt = Annotated[
    Path | None,
    typer.Option("--into-take", help="Also store the result in this take (/calibration/<device>)."),
]


def _store_intrinsics(take: Path | None, result: IntrinsicsResult, source: str) -> None:
    if take is not None:
        store_calibration(take, result.camera, intrinsics=result.summary(), source=source)


@calibrate_app.command("intrinsics")
def intrinsics_cmd(
    images: Annotated[list[Path], typer.Argument(help="Images of the board (one camera).")],
    board: BoardOpt,
    out: OutOpt,
    json_out: JsonOpt = False,
    report: ReportOpt = None,
    camera: Annotated[str, typer.Option("--camera", help="Camera name stored in the result.")] = "cam0",
    model: ModelOpt = "auto",
    into_take: IntoTakeOpt = None,
) -> None:
    """Intrinsics of one camera from image files, with lens-model selection."""
    try:
        spec = parse_board(board)
        result = calibrate_images(images, spec, camera=camera, model=model)
        write_result(result, out)
        _store_intrinsics(into_take, result, f"calibrate intrinsics ({len(images)} images)")
        if report is not None:
            write_report(report, [result], samples={camera: load_image(images[0])})
    except RigdError as exc:
        raise _fail(exc) from exc
    _warn(result)
    if json_out:
        typer.echo(dumps_summary(result))
    else:
        _err.print(
            f"{camera}: model {result.model}, RMS {result.rms_px:.4f} px, {len(result.views)} views -> {out}"
        )


def _view_key(path: str, index: int) -> str:
    """View id of an image file: the last number in its stem (left07.png -> 07), else its index."""
    nums = re.findall(r"\d+", Path(path).stem)
    return nums[-1].lstrip("0") or "0" if nums else str(index)


def _parse_camera_globs(cameras: list[str]) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for item in cameras:
        name, sep, pattern = item.partition("=")
        if not sep or not name or not pattern:
            raise typer.BadParameter(f"{item!r}: expected NAME=GLOB, e.g. left='imgs/left*.png'")
        files = sorted(glob.glob(pattern))
        if not files:
            raise typer.BadParameter(f"{item!r}: no file matches {pattern!r}")
        out[name] = files
    return out


def _rig_from_images(
    spec: BoardSpec, sets: dict[str, list[str]], model: str
) -> tuple[dict[str, IntrinsicsResult], dict[str, dict[str, Detection]]]:
    intr: dict[str, IntrinsicsResult] = {}
    views: dict[str, dict[str, Detection]] = {}
    for cam, files in sets.items():
        dets, rej, warn = detect_images(files, spec)
        keys = {Path(f).name: _view_key(f, i) for i, f in enumerate(files)}
        intr[cam] = calibrate_intrinsics(dets, spec, camera=cam, model=model, rejected=rej, warnings=warn)
        for d in dets:
            views.setdefault(keys[d.name], {})[cam] = d
    return intr, views


def _rig_from_take(
    spec: BoardSpec,
    take_path: Path,
    model: str,
    events: bool = False,
    event_params: ReconstructionParams | None = None,
) -> tuple[dict[str, IntrinsicsResult], dict[str, dict[str, Detection]]]:
    """Detect the board in every frame of every camera of a take; frames of one trigger pulse
    (same pulse_index) form one view.

    With `events`, every event sensor joins the rig too: frames are reconstructed from its events
    (`calibration.e2calib`, accurate method) at the mid-exposure instant of each RGB frame of
    the first camera and labelled with that frame's pulse, so an event view and the RGB views of
    one pulse show the same board pose and the joint refinement ties the sensor into the rig frame.
    """
    from rigd.take.reader import open_take

    intr: dict[str, IntrinsicsResult] = {}
    views: dict[str, dict[str, Detection]] = {}
    with open_take(take_path) as take:
        for cam in take.cameras:
            series = take.frames(cam)
            dets: list[Detection] = []
            rej: list[RejectedView] = []
            for i in range(len(series)):
                frame = series[i]
                key = str(frame.pulse_index if frame.pulse_index >= 0 else i)
                d = detect(np.asarray(frame.image), spec, name=f"{cam}#{key}")
                if d is None:
                    rej.append(RejectedView(name=f"{cam}#{key}", reason=f"board {spec} not found"))
                    continue
                dets.append(d)
                views.setdefault(key, {})[cam] = d
            if not dets:
                log.warning("take %s: board not found in any frame of camera %s", take_path, cam)
                continue
            intr[cam] = calibrate_intrinsics(dets, spec, camera=cam, model=model, rejected=rej)
        if events and take.event_sensors:
            if not take.cameras or not len(take.frames(take.cameras[0])):
                raise RigdError(
                    f"{take_path}: --events needs RGB frames: their trigger pulses are the instants "
                    "the event views are reconstructed at"
                )
            series = take.frames(take.cameras[0])
            keys = [
                str(series[i].pulse_index if series[i].pulse_index >= 0 else i) for i in range(len(series))
            ]
            times = np.asarray(series.timestamps_us, np.int64) + np.asarray(
                [series[i].exposure_us // 2 for i in range(len(series))], np.int64
            )
            for sensor in take.event_sensors:
                ev = take.events(sensor)
                if len(ev) == 0:
                    log.warning(
                        "take %s: event sensor %s has no events; left out of the rig", take_path, sensor
                    )
                    continue
                found = detect_in_reconstructions(
                    ev,
                    take.geometry(sensor),
                    times,
                    spec,
                    params=event_params,
                    names=[f"{sensor}#{k}" for k in keys],
                    sensor=sensor,
                )
                if not found.detections:
                    log.warning("take %s: board not found in any reconstruction of %s", take_path, sensor)
                    continue
                for k in keys:
                    d = found.detections.get(f"{sensor}#{k}")
                    if d is not None:
                        views.setdefault(k, {})[sensor] = d
                intr[sensor] = calibrate_intrinsics(
                    list(found.detections.values()), spec, camera=sensor, model=model, rejected=found.rejected
                )
                log.info(
                    "take %s: %s: board in %d/%d reconstructions, RMS %.3f px",
                    take_path,
                    sensor,
                    len(found.detections),
                    len(keys),
                    intr[sensor].rms_px,
                )
    return intr, views


@calibrate_app.command("rig")
def rig_cmd(
    board: BoardOpt,
    out: OutOpt,
    take: Annotated[Path | None, typer.Argument(help="Take whose frames show the board.")] = None,
    camera: Annotated[
        list[str] | None, typer.Option("--camera", "-c", help="NAME=GLOB image set of one camera (repeat).")
    ] = None,
    reference: Annotated[
        str | None, typer.Option("--reference", help="Camera defining the rig frame.")
    ] = None,
    kalibr: Annotated[
        Path | None, typer.Option("--kalibr", help="Also write a Kalibr camchain YAML.")
    ] = None,
    json_out: JsonOpt = False,
    report: ReportOpt = None,
    model: ModelOpt = "auto",
    into_take: IntoTakeOpt = None,
    events: Annotated[
        bool,
        typer.Option(
            "--events",
            help="Take only: include the event sensors, from frames reconstructed at the RGB trigger pulses.",
        ),
    ] = False,
) -> None:
    """Intrinsics of every camera and their poses in one rig frame, from simultaneous board views.

    Views are matched by trigger pulse (take) or by the last number in the file names (image sets).
    With --events, the take's event sensors are calibrated e2calib-style and posed in the same
    rig frame, jointly refined with the cameras.
    """
    if (take is None) == (not camera):
        raise _fail(ValueError("give either a TAKE or --camera NAME=GLOB sets (at least two)"))
    try:
        spec = parse_board(board)
        if events and take is None:
            raise RigdError("--events needs a TAKE (event sensors have no image files)")
        if take is not None:
            intr, views = _rig_from_take(spec, take, model, events=events)
        else:
            intr, views = _rig_from_images(spec, _parse_camera_globs(camera or []), model)
        rig = calibrate_rig(intr, views, spec, reference=reference)
        if out.suffix.lower() == ".json":
            write_json(rig, out)
        else:
            write_opencv_yaml(intr, out, rig)
        if kalibr is not None:
            write_kalibr_camchain(intr, kalibr, rig)
        if into_take is not None:
            for pose in rig.cameras:
                store_calibration(
                    into_take,
                    pose.camera,
                    intrinsics=intr[pose.camera].summary(),
                    pose=pose.model_dump(),
                    source=f"calibrate rig (reference {rig.reference})",
                )
        if report is not None:
            write_report(report, list(intr.values()), rig)
    except RigdError as exc:
        raise _fail(exc) from exc
    for r in intr.values():
        _warn(r)
    _warn(rig)
    if json_out:
        typer.echo(dumps_summary(rig))
    else:
        for c in rig.cameras:
            _err.print(f"{c.camera}: t={np.round(c.t, 4).tolist()} m, RMS {c.rms_px:.3f} px")


def event_times(take_path: Path, sensor: str, rate_hz: float | None = None) -> np.ndarray:
    """Times (take clock, us) to reconstruct a sensor's frames at: every `rate_hz` over its event
    span, else the cameras' mid-exposure instants (the pulses the RGB frames show, so event and
    RGB views of one pulse see the same board pose), else the sensor's rising trigger edges."""
    from rigd.take.reader import open_take

    with open_take(take_path) as take:
        if sensor not in take.event_sensors:
            raise RigdError(f"{take_path}: no event sensor {sensor!r} (has {take.event_sensors})")
        if rate_hz is not None:
            if rate_hz <= 0:
                raise RigdError(f"--rate must be > 0 Hz, got {rate_hz}")
            span = take.event_span(sensor)
            if span is None:
                raise RigdError(f"{take_path}: event sensor {sensor!r} has no events")
            return np.arange(span[0], span[1], 1e6 / rate_hz).astype(np.int64)
        if take.cameras:
            cam = take.frames(take.cameras[0])
            if len(cam):
                return np.asarray(cam.timestamps_us + cam[0].exposure_us // 2, np.int64)
        trig = take.triggers(sensor)
        return np.asarray(trig.t[trig.p == 1], np.int64)


def calibrate_take_events(
    take_path: Path,
    sensor: str,
    spec: BoardSpec,
    methods: list[str],
    rate_hz: float | None = None,
    params: ReconstructionParams | None = None,
    model: str = "k1k2",
) -> E2CalibResult:
    """e2calib on one sensor of a take (see calibration.e2calib)."""
    from rigd.take.reader import open_take

    times = event_times(take_path, sensor, rate_hz)
    with open_take(take_path) as take:
        events = take.events(sensor)
        size = take.geometry(sensor)
    return calibrate_events(
        events, size, times, spec, sensor=sensor, methods=methods, params=params, model=model
    )


@calibrate_app.command("events")
def events_cmd(
    take: Annotated[Path, typer.Argument(help="Take holding the sensor's events of a moving board.")],
    sensor: Annotated[str, typer.Option("--sensor", "-s", help="Event sensor name in the take.")],
    board: BoardOpt,
    out: OutOpt,
    json_out: JsonOpt = False,
    method: Annotated[
        list[str] | None,
        typer.Option(
            "--method", "-m", help=f"Reconstruction method(s): {', '.join(METHODS)} (default: all)."
        ),
    ] = None,
    rate: Annotated[
        float | None,
        typer.Option("--rate", help="Reconstruct at this rate (Hz) instead of the trigger pulses."),
    ] = None,
    cutoff_hz: Annotated[float, typer.Option("--cutoff-hz", help="hpf method: high-pass corner.")] = 1.0,
    model: ModelOpt = "k1k2",
    into_take: Annotated[
        bool, typer.Option("--into-take", help="Also store the result in TAKE (/calibration/<sensor>).")
    ] = False,
) -> None:
    """Intrinsics of an event sensor from frames reconstructed from its events (e2calib-style).

    Every method is run and reported; the one with the lowest RMS is written to --out."""
    methods = method or list(METHODS)
    try:
        spec = parse_board(board)
        res = calibrate_take_events(
            take, sensor, spec, methods, rate, ReconstructionParams(cutoff_hz=cutoff_hz), model=model
        )
        best = res.best()
        assert best.intrinsics is not None
        write_result(best.intrinsics, out)
        if into_take:
            summary = best.intrinsics.summary()
            summary["camera"] = sensor
            store_calibration(take, sensor, intrinsics=summary, source=f"calibrate events ({best.method})")
    except RigdError as exc:
        raise _fail(exc) from exc
    _warn(best.intrinsics)
    table = [
        {
            "method": m.method,
            "frames": m.frames,
            "detected": m.detected,
            "rms_px": m.intrinsics.rms_px if m.intrinsics else None,
            "K": m.intrinsics.K if m.intrinsics else None,
            "error": m.error,
            "time_s": round(m.total_s, 3),
        }
        for m in res.methods
    ]
    if json_out:
        summary = best.intrinsics.summary()
        summary["method"] = best.method
        summary["methods"] = table
        typer.echo(json.dumps(summary, indent=2))
    else:
        for row in table:
            rms = f"{row['rms_px']:.3f} px" if row["rms_px"] is not None else f"failed ({row['error']})"
            _err.print(
                f"{sensor} {row['method']}: {row['detected']}/{row['frames']} frames, "
                f"RMS {rms}, {row['time_s']} s"
            )
        _err.print(f"{sensor}: best {best.method} -> {out}")
