"""`rigd calibrate guided --camera CAM`: live guided intrinsic calibration in the terminal.

Opens the rig's trigger and one camera (the built-in sim rig watching a moving board unless
`--config` is given), streams frames into `calibration.guided.GuidedSession`, shows its feedback
(a live panel on a terminal, one line per frame otherwise, so logs and tests see every decision)
and stops when the target uncertainty is reached or `--max-seconds` runs out. The calibration is
written with `calibration.io.write_result` whenever enough views were kept.

Exit codes: 0 target reached, 1 time ran out first (the file is still written when at least 3
views were kept), 2 on an error (message on stderr), as the other calibrate commands.
Register with `calibrate_app.command("guided")(guided)`.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.console import Console, Group
from rich.live import Live
from rich.table import Table
from rich.text import Text

from calibration.boards import parse_board
from calibration.guided import TILT_BINS, Feedback, GuidedSession
from calibration.io import dumps_summary, write_result
from drivers.base import RgbCamera, Trigger
from drivers.registry import open_device
from rigd.app.config import CameraConfig, RigConfig, default_sim_rig
from rigd.core.errors import RigdError

log = logging.getLogger(__name__)

_err = Console(stderr=True)

#: World of the default sim rig: its own, so that a board scene never clashes with a sprites
#: scene another command of the same process made in the "default" world.
SIM_WORLD = "guided"


def _parse_resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise typer.BadParameter(f"{text!r}: expected WIDTHxHEIGHT, e.g. 640x360") from exc
    if w < 16 or h < 16:
        raise typer.BadParameter(f"{text!r}: too small")
    return w, h


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


def _status_line(fb: Feedback, camera: str) -> str:
    sig = " ".join(f"{k}={v:.2f}" for k, v in fb.sigmas.items()) or "sigmas: need more views"
    mark = "CAPTURED" if fb.captured else ("DONE" if fb.done else "-")
    return f"{camera} {mark} views={fb.n_views} {sig} | {fb.reason} | next: {fb.next_hint}"


def _panel(fb: Feedback, camera: str, session: GuidedSession, target: float, left_s: float) -> Group:
    """The live view: status, sigmas vs target, coverage grid (views per cell; tilt bins seen)."""
    head = Text.assemble(
        (f"{camera}  ", "bold"),
        ("CAPTURED  " if fb.captured else "", "bold green"),
        (f"views {fb.n_views}  ", ""),
        (f"{left_s:.0f} s left", "dim"),
    )
    state = Text(
        f"board {'found' if fb.detected else 'not found'}; still {'yes' if fb.still else 'no'}"
        + (f" ({fb.motion_px:.1f} px)" if fb.motion_px is not None else "")
        + f"; sharp {'yes' if fb.sharp else 'no'} - {fb.reason}"
    )
    sig = Table(title=f"std dev (target {target:g} px)", show_header=True)
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


def guided(
    camera: Annotated[str, typer.Option("--camera", "-c", help="RGB camera of the rig to calibrate.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output: .yaml/.yml/.xml (OpenCV) or .json.")],
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
        typer.Option("--still-px", help="Still below this corner motion per frame (px)."),
    ] = 1.0,
    min_views: Annotated[int, typer.Option("--min-views", help="Views before the first calibration.")] = 6,
    model: Annotated[str, typer.Option("--model", help="Lens model of the session and the result.")] = "k1k2",
    resolution: Annotated[
        str, typer.Option("--resolution", help="Frame size of the built-in sim rig (ignored with --config).")
    ] = "640x360",
    json_out: Annotated[bool, typer.Option("--json", help="Print the result as JSON on stdout.")] = False,
) -> None:
    """Guided intrinsic calibration: show the board where told until the uncertainty target is met."""
    try:
        if config is not None:
            cfg = RigConfig.load(config)
        else:
            cfg = default_sim_rig(
                world=SIM_WORLD, resolution=_parse_resolution(resolution), pixel_format="mono8"
            )
        cam_cfg = _camera_config(cfg, camera)
        spec = parse_board(board)
        trigger, cam = _open(cfg, cam_cfg)
    except RigdError as exc:
        _err.print(f"[bold red]error:[/] {exc}")
        raise typer.Exit(code=2) from exc

    shape = cam.frame_shape
    session = GuidedSession(
        spec,
        (int(shape[1]), int(shape[0])),
        target_sigma_px=target_sigma,
        still_px=still_px,
        min_views=min_views,
        model=model,
    )
    _err.print(f"{camera}: {cam_cfg.spec}; {shape[1]}x{shape[0]}; first: {session.hint_text()}")
    live = Live(console=_err, refresh_per_second=8, transient=False) if _err.is_terminal else None
    frames = skipped = 0
    try:
        cam.start()
        trigger.arm()
        trigger.start()
        t_end = time.monotonic() + max_seconds
        if live is not None:
            live.start()
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
            if live is not None:
                live.update(_panel(fb, camera, session, target_sigma, t_end - time.monotonic()))
            else:
                _err.print(_status_line(fb, camera), markup=False, highlight=False, soft_wrap=True)
    except RigdError as exc:
        _err.print(f"[bold red]error:[/] {exc}")
        raise typer.Exit(code=2) from exc
    finally:
        if live is not None:
            live.stop()
        for stop in (trigger.stop, cam.stop, cam.close, trigger.close):
            try:
                stop()
            except Exception as stop_exc:  # noqa: BLE001  (shutdown must reach every device)
                log.error("guided: %s failed during shutdown: %s", stop.__qualname__, stop_exc)

    log.info("guided: %d frames looked at, %d stale frames skipped", frames, skipped)
    done = session.done
    if len(session.views) < 3:
        _err.print(
            f"[bold red]{camera}: only {len(session.views)} view(s) captured in {max_seconds:g} s; "
            "nothing written[/]"
        )
        raise typer.Exit(code=1)
    try:
        result = session.result(camera=camera)
        write_result(result, out)
    except RigdError as exc:
        _err.print(f"[bold red]error:[/] {exc}")
        raise typer.Exit(code=2) from exc
    for w in result.warnings:
        _err.print(f"[yellow]warning:[/] {w}")
    sig = ", ".join(f"{k} {result.std_devs[k]:.3f}" for k in ("fx", "fy", "cx", "cy"))
    verdict = "target reached" if done else f"time ran out before the {target_sigma:g} px target"
    _err.print(
        f"{camera}: {verdict}; {len(result.views)} views, model {result.model}, "
        f"RMS {result.rms_px:.3f} px, std dev (px) {sig} -> {out}"
    )
    if json_out:
        typer.echo(dumps_summary(result))
    if not done:
        raise typer.Exit(code=1)
