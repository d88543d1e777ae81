"""`rigd calibrate guided --camera CAM`: live guided intrinsic calibration in the terminal.

Parses the arguments, runs `rigd.app.workflows.guided` (the built-in sim rig watching a moving
board unless `--config` is given) and shows its feedback: a live panel on a terminal; otherwise a
line per captured view and a status line at most every STATUS_EVERY_S seconds (a line per frame
made thousands of lines a session), never wrapped.

Exit codes: 0 target reached, 1 time ran out first (the file is still written when at least 3
views were kept), 2 on an error (message on stderr), as the other calibrate commands.
Register with `calibrate_app.command("guided")(guided)`.
"""

from __future__ import annotations

import time
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.console import Console, Group
from rich.live import Live
from rich.markup import escape
from rich.table import Table
from rich.text import Text

from rigd.app.commands.consoles import fail, stderr_console
from rigd.app.commands.flags import sim_clock_flag
from rigd.core.errors import RigdError

if TYPE_CHECKING:  # the session (OpenCV, scipy) and the rig load when the command runs
    from calibration.guided import Feedback, GuidedSession
    from rigd.app.workflows.guided import GuidedOptions, GuidedOutcome, GuidedProgress

_err = stderr_console()


def _parse_resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise typer.BadParameter(f"{text!r}: expected WIDTHxHEIGHT, e.g. 640x360") from exc
    if w < 16 or h < 16:
        raise typer.BadParameter(f"{text!r}: too small")
    return w, h


#: Off a terminal, a status line (besides a line per captured view) at most this often.
STATUS_EVERY_S = 5.0


def _views(fb: Feedback) -> str:
    """Views kept, and how many the written fit uses once it runs (the count the result reports)."""
    if fb.n_used is None or fb.n_used == fb.n_views:
        return f"views={fb.n_views}"
    return f"views={fb.n_used} ({fb.n_views} kept, {fb.n_views - fb.n_used} rejected as outliers)"


def _status_line(fb: Feedback, camera: str, left_s: float) -> str:
    sig = " ".join(f"{k}={v:.2f}" for k, v in fb.sigmas.items()) or "sigmas: need more views"
    mark = "CAPTURED" if fb.captured else ("DONE" if fb.done else "-")
    return (
        f"{camera} {mark} {_views(fb)} {sig} | {fb.reason} | next: {fb.next_hint} | "
        f"{max(0.0, left_s):.0f} s left"
    )


class _Lines:
    """Off a terminal: a line per captured view, the final state, else one every STATUS_EVERY_S."""

    def __init__(self, console: Console, camera: str) -> None:
        self.console = console
        self.camera = camera
        self.last = -float("inf")

    def __call__(self, fb: Feedback, left_s: float) -> None:
        now = time.monotonic()
        if not (fb.captured or fb.done or now - self.last >= STATUS_EVERY_S):
            return
        self.last = now
        self.console.print(
            _status_line(fb, self.camera, left_s), markup=False, highlight=False, soft_wrap=True
        )


def _panel(fb: Feedback, camera: str, session: GuidedSession, target: float, left_s: float) -> Group:
    """The live view: status, sigmas vs target, coverage grid (views per cell; tilt bins seen)."""
    from calibration.view_planning import TILT_BINS

    head = Text.assemble(
        (f"{camera}  ", "bold"),
        ("CAPTURED  " if fb.captured else "", "bold green"),
        (f"{_views(fb).replace('=', ' ')}  ", ""),
        (f"{max(0.0, left_s):.0f} s left", "dim"),
    )
    state = Text(
        f"board {'found' if fb.detected else 'not found'}; still {'yes' if fb.still else 'no'}"
        + (f" ({fb.motion_px:.1f} px)" if fb.motion_px is not None else "")
        + f"; sharp {'yes' if fb.sharp else 'no'} - {fb.reason}"
    )
    fit = "written fit" if fb.n_used is not None else "running fit"
    sig = Table(title=f"std dev, {fit} (target {target:g} px)", show_header=True)
    for n in ("fx", "fy", "cx", "cy"):
        sig.add_column(n, justify="right")
    if fb.sigmas:
        sig.add_row(
            *(
                Text(f"{fb.sigmas[n]:.3f}", style="green" if fb.sigmas[n] <= target else "yellow")
                for n in ("fx", "fy", "cx", "cy")
            )
        )
    else:
        sig.add_row(*(["-"] * 4))
    cols, rows = session.grid
    cov = Table(title="coverage (views; tilt bins seen)", show_header=False, show_lines=True)
    for _ in range(cols):
        cov.add_column(justify="center")
    abbrev = {"facing": "F", "right-away": "R", "left-away": "L", "bottom-away": "B", "top-away": "T"}
    for r in range(rows):
        cells = []
        for c in range(cols):
            counts = fb.coverage[r * cols + c]
            seen = "".join(abbrev[t] for t, k in zip(TILT_BINS, counts, strict=True) if k)
            cells.append(f"{sum(counts)} {seen}" if sum(counts) else ".")
        cov.add_row(*cells)
    hint = Text(
        ("DONE: " if fb.done else "next: ") + fb.next_hint, style="bold green" if fb.done else "bold cyan"
    )
    return Group(head, state, sig, cov, hint)


def guided(
    camera: Annotated[
        str,
        typer.Option(
            "--camera",
            "-c",
            help="RGB camera (or event sensor, through frames reconstructed from its events).",
        ),
    ],
    out: Annotated[
        Path | None,
        typer.Option(
            "--out",
            "-o",
            help="Output: .yaml/.yml/.xml (OpenCV) or .json; default "
            "TAKE_DIR/calibration/CAMERA-<UTC time>.yaml (TAKE_DIR: the config's service.take_dir, takes).",
        ),
    ] = None,
    report: Annotated[Path | None, typer.Option("--report", help="Also write an HTML report here.")] = None,
    config: Annotated[
        Path | None,
        typer.Option("--config", help="Rig config (default: the built-in sim rig watching a moving board)."),
    ] = None,
    board: Annotated[
        str, typer.Option("--board", "-b", help="Board spec (default: the sim rig's board).")
    ] = "chessboard:9x6:0.08",
    target_sigma: Annotated[
        float, typer.Option("--target-sigma", help="Stop when fx, fy, cx, cy std devs are all <= this (px).")
    ] = 0.5,
    max_seconds: Annotated[float, typer.Option("--max-seconds", help="Give up after this long.")] = 120.0,
    still_px: Annotated[
        float,
        typer.Option("--still-px", help="Still: the board smears less than this in one exposure (px)."),
    ] = 1.0,
    min_views: Annotated[
        int,
        typer.Option(
            "--min-views",
            help="Views before the first calibration; the session is done once the written fit uses "
            "max(this, 10) views (the report's recommendation) and meets the target.",
        ),
    ] = 6,
    model: Annotated[str, typer.Option("--model", help="Lens model of the session and the result.")] = "k1k2",
    resolution: Annotated[
        str, typer.Option("--resolution", help="Frame size of the built-in sim rig (ignored with --config).")
    ] = "640x360",
    sim_clock: Annotated[
        str,
        typer.Option(
            "--sim-clock",
            help="real, or virtual: the built-in sim rig runs as fast as the CPU allows, every frame is "
            "looked at and --max-seconds counts the camera's time: the same session on any machine.",
        ),
    ] = "real",
    json_out: Annotated[bool, typer.Option("--json", help="Print the result as JSON on stdout.")] = False,
) -> None:
    """Guided intrinsic calibration: show the board where told until the uncertainty target is met."""
    from rigd.app.workflows.guided import GuidedFrame, GuidedOptions, run_guided

    clock = sim_clock_flag(sim_clock, config, "the built-in sim rig")
    sim_resolution = _parse_resolution(resolution) if config is None else None
    live = Live(console=_err, refresh_per_second=8, transient=False) if _err.is_terminal else None
    lines = _Lines(_err, camera)

    def show(update: GuidedProgress) -> None:
        if not isinstance(update, GuidedFrame):
            _err.print(
                f"{camera}: {update.spec}; {update.frame_size[0]}x{update.frame_size[1]}; "
                f"first: {update.first_hint}",
                markup=False,
                highlight=False,
                soft_wrap=True,
            )
            if live is not None:
                live.start()
        elif live is not None:
            live.update(_panel(update.feedback, camera, update.session, target_sigma, update.seconds_left))
        else:
            lines(update.feedback, update.seconds_left)

    try:
        # One keyword per flag; alike in shape to the other commands' option models, nothing shared.
        options = GuidedOptions(
            camera=camera,
            out=out if out is not None else default_out(camera, config),
            report=report,
            config=config,
            board=board,
            target_sigma_px=target_sigma,
            max_seconds=max_seconds,
            still_px=still_px,
            min_views=min_views,
            model=model,
            resolution=sim_resolution,
            sim_clock=clock,
        )
        outcome = run_guided(options, show)
    except RigdError as exc:
        raise fail(exc) from exc
    finally:
        if live is not None:
            live.stop()
    _report(outcome, options, json_out)


def default_out(camera: str, config: Path | None) -> Path:
    """Where a session writes without `--out`: beside the takes, in the calibration directory
    the web console uses too (`<take_dir>/calibration`), under a name no earlier session has,
    so neither the working directory nor an earlier calibration is written over unasked."""
    from rigd.app.config import RigConfig, ServiceConfig

    take_dir = RigConfig.load(config).service.take_dir if config is not None else ServiceConfig().take_dir
    base = f"{camera}-{datetime.now(UTC).strftime('%Y%m%dT%H%M%SZ')}"
    out, n = take_dir / "calibration" / f"{base}.yaml", 1
    while out.exists():
        n += 1
        out = out.with_name(f"{base}-{n}.yaml")
    out.parent.mkdir(parents=True, exist_ok=True)
    return out


def _report(outcome: GuidedOutcome, options: GuidedOptions, json_out: bool) -> None:
    """The verdict on stderr (JSON on stdout); exit 1 unless the target was reached."""
    from calibration.io import dumps_summary
    from rigd.app.workflows.guided import verdict, views_text

    reached, text = verdict(outcome, options.target_sigma_px, options.done_views)
    result = outcome.result
    if result is None:
        _err.print(f"[bold red]{outcome.camera}: {text} in {options.max_seconds:g} s[/]")
        raise typer.Exit(code=1)
    for w in result.warnings:
        _err.print(f"[yellow]warning:[/] {escape(w)}", soft_wrap=True, highlight=False)
    sig = ", ".join(f"{k} {result.std_devs[k]:.3f}" for k in ("fx", "fy", "cx", "cy"))
    written = str(options.out_path) + (f" (report {options.report})" if options.report else "")
    _err.print(
        f"{outcome.camera}: {text}; {views_text(outcome)}, model {result.model}, "
        f"RMS {result.rms_px:.3f} px, std dev (px) {sig} -> {written}",
        markup=False,
        highlight=False,
        soft_wrap=True,
    )
    if json_out:
        typer.echo(dumps_summary(result))
    if not reached:
        raise typer.Exit(code=1)
