"""`rigd calibrate ...`: intrinsics from image files, rig extrinsics from image sets or a take,
event-sensor intrinsics from a take.

The commands parse arguments, call `rigd.products.calibrate` and print what it returns.
Register with `app.add_typer(calibrate_app, name="calibrate")`. Exit code 2 on a RigdError, with
the message on stderr; `--json` prints the result on stdout.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.markup import escape

from rigd.app.commands.consoles import fail, stderr_console
from rigd.app.commands.help import RigdTyper
from rigd.app.commands.progress import StageProgress
from rigd.core.errors import RigdError

if TYPE_CHECKING:  # the calibration libraries (OpenCV, scipy, numba) load when a command runs
    from calibration.extrinsics import RigResult
    from calibration.intrinsics import IntrinsicsResult
    from rigd.products.calibrate import EventsCalibration, ImageSets, RigCalibration

#: calibration.e2calib.METHODS, spelled out so that `--help` need not import the library
#: (tests/app/commands/test_calibrate_cmd.py holds the two equal).
E2CALIB_METHODS = ("window", "hpf", "integrate")

calibrate_app = RigdTyper(
    help="Calibrate cameras: intrinsics, event-sensor intrinsics (e2calib), rig extrinsics.",
    no_args_is_help=True,
)
_err = stderr_console()

BoardOpt = Annotated[str, typer.Option("--board", "-b", help="Board spec, e.g. chessboard:9x6:0.025.")]
OutOpt = Annotated[Path, typer.Option("--out", "-o", help="Output file: .yaml/.yml/.xml (OpenCV) or .json.")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print the result as JSON on stdout.")]
ReportOpt = Annotated[Path | None, typer.Option("--report", help="Write an HTML report here.")]
ModelOpt = Annotated[
    str, typer.Option("--model", help="Lens model, or 'auto' for cross-validated selection.")
]


def _warn(result: IntrinsicsResult | RigResult) -> None:
    """Say the result's warnings, once: the library returns them instead of logging them."""
    from calibration.intrinsics import IntrinsicsResult

    who = f"{result.camera}: " if isinstance(result, IntrinsicsResult) else "rig: "
    for w in result.warnings:
        _err.print(f"[yellow]warning:[/] {who}{escape(w)}", soft_wrap=True, highlight=False)
    for r in getattr(result, "rejected", []):
        _err.print(f"[yellow]rejected:[/] {r.name}: {r.reason}")


def _stored(take: Path, devices: list[str]) -> None:
    """Confirm `--into-take`: where in the take each device's calibration now sits."""
    where = ", ".join(f"/calibration/{d}" for d in devices)
    _err.print(f"stored in {take}: {where}", soft_wrap=True, highlight=False, markup=False)


IntoTakeOpt = Annotated[
    Path | None,
    typer.Option("--into-take", help="Also store the result in this take (/calibration/<device>)."),
]


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
    allow_few_views: Annotated[
        bool,
        typer.Option("--allow-few-views", help="Calibrate even when most images do not show the board."),
    ] = False,
) -> None:
    """Intrinsics of one camera from image files, with lens-model selection."""
    from calibration.io import dumps_summary
    from rigd.products.calibrate import IntrinsicsOptions, run_intrinsics

    try:
        shared: dict[str, Any] = {
            "out": out,
            "model": model,
            "report": report,
            "into_take": into_take,
            "allow_few_views": allow_few_views,
        }
        options = IntrinsicsOptions(images=images, board=board, camera=camera, **shared)
        with StageProgress(_err, "calibrate intrinsics", quiet=json_out) as bar:
            result = run_intrinsics(options, bar)
    except RigdError as exc:
        raise fail(exc) from exc
    _warn(result)
    if json_out:
        typer.echo(dumps_summary(result))
    else:
        _err.print(
            f"{camera}: model {result.model}, RMS {result.rms_px:.4f} px, {len(result.views)} views -> {out}"
        )
    if into_take is not None:
        _stored(into_take, [camera])


def _image_sets(cameras: list[str]) -> ImageSets:
    """`NAME=GLOB` options as image files per camera; a usage error names the option at fault."""
    from rigd.products.calibrate import ImageSets, glob_images

    files: dict[str, list[Path]] = {}
    for item in cameras:
        name, sep, pattern = item.partition("=")
        if not sep or not name or not pattern:
            raise typer.BadParameter(f"{item!r}: expected NAME=GLOB, e.g. left='imgs/left*.png'")
        files[name] = glob_images(pattern)
        if not files[name]:
            raise typer.BadParameter(f"{item!r}: no file matches {pattern!r}")
    return ImageSets(files=files)


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
    from calibration.boards import parse_board
    from calibration.io import dumps_summary
    from rigd.products.calibrate import RigOptions, TakeSource, run_rig
    from rigd.products.calibration_truth import ground_truth_of, rig_errors

    if (take is None) == (not camera):
        raise fail(ValueError("give either a TAKE or --camera NAME=GLOB sets (at least two)"))
    try:
        spec = parse_board(board)
        if events and take is None:
            raise RigdError("--events needs a TAKE (event sensors have no image files)")
        source = TakeSource(path=take, events=events) if take is not None else _image_sets(camera or [])
        shared: dict[str, Any] = {"out": out, "model": model, "report": report, "into_take": into_take}
        options = RigOptions(board=spec, source=source, reference=reference, kalibr=kalibr, **shared)
        truth = ground_truth_of(take) if take is not None else {}
        with StageProgress(_err, "calibrate rig", quiet=json_out) as bar:
            calib = run_rig(options, bar)
    except RigdError as exc:
        raise fail(exc) from exc
    for r in calib.intrinsics.values():
        _warn(r)
    _warn(calib.rig)
    if json_out:
        typer.echo(dumps_summary(calib.rig))
    else:
        _print_rig(calib, out)
    poses = {c.camera: (c.R, c.t) for c in calib.rig.cameras}
    cams = {name: r.K for name, r in calib.intrinsics.items()}
    for e in rig_errors(truth, cams, poses, calib.rig.reference):
        _err.print(e.line(), soft_wrap=True, highlight=False)
    if into_take is not None:
        _stored(into_take, [pose.camera for pose in calib.rig.cameras])


def _print_rig(calib: RigCalibration, out: Path) -> None:
    """Each device's place in the rig and its two reprojection RMS values, each named for the fit
    it comes from (they differ: see the report's rig section)."""
    import numpy as np

    rig = calib.rig
    _err.print(
        f"rig frame: {rig.reference} (x right, y down, z forward, m); {rig.n_views} shared views, "
        f"joint RMS {rig.rms_px:.3f} px -> {out}",
        highlight=False,
    )
    for c in rig.cameras:
        if c.camera == rig.reference:
            where = "the reference (origin of the rig frame)"
        else:
            centre = ", ".join(f"{v:+.4f}" for v in c.center_m)
            std = max(c.t_std_m, default=0.0)
            turn = float(np.degrees(np.linalg.norm(c.rvec)))
            where = f"centre at ({centre}) m ±{std:.4f} m in {rig.reference}'s frame, rotated {turn:.2f}°"
        own = calib.intrinsics[c.camera]
        _err.print(
            f"{c.camera}: {where}; RMS {own.rms_px:.3f} px own fit ({len(own.views)} views, "
            f"avg_reprojection_error), {c.rms_px:.3f} px rig fit ({c.n_views} shared views, intrinsics "
            "fixed, one board pose per view for all cameras)",
            soft_wrap=True,
            highlight=False,
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
            "--method", "-m", help=f"Reconstruction method(s): {', '.join(E2CALIB_METHODS)} (default: all)."
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
    from rigd.products.calibrate import EventsOptions, run_events
    from rigd.products.calibration_truth import ground_truth_of, intrinsics_error

    try:
        options = EventsOptions(
            take=take,
            sensor=sensor,
            board=board,
            out=out,
            methods=method or list(E2CALIB_METHODS),
            rate_hz=rate,
            cutoff_hz=cutoff_hz,
            model=model,
            into_take=into_take,
        )
        truth = ground_truth_of(take)
        with StageProgress(_err, "calibrate events", quiet=json_out) as bar:
            calib = run_events(options, bar)
    except RigdError as exc:
        raise fail(exc) from exc
    if sensor in truth:
        _err.print(intrinsics_error(sensor, truth[sensor], calib.intrinsics.K).line(), highlight=False)
    _warn(calib.intrinsics)
    table = _method_table(calib)
    if json_out:
        summary = calib.intrinsics.summary()
        summary["method"] = calib.best.method
        summary["methods"] = table
        typer.echo(json.dumps(summary, indent=2))
    else:
        for row in table:
            rms = f"{row['rms_px']:.3f} px" if row["rms_px"] is not None else f"failed ({row['error']})"
            _err.print(
                f"{sensor} {row['method']}: {row['detected']}/{row['frames']} frames, "
                f"RMS {rms}, {row['time_s']} s"
            )
        _err.print(f"{sensor}: best {calib.best.method} -> {out}")
    if into_take:
        _stored(take, [sensor])


def _method_table(calib: EventsCalibration) -> list[dict[str, object]]:
    """One row per reconstruction method, as `--json` prints it."""
    return [
        {
            "method": m.method,
            "frames": m.frames,
            "detected": m.detected,
            "rms_px": m.intrinsics.rms_px if m.intrinsics else None,
            "K": m.intrinsics.K if m.intrinsics else None,
            "error": m.error,
            "time_s": round(m.total_s, 3),
        }
        for m in calib.result.methods
    ]
