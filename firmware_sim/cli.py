"""`rigd simulate-events`: frames (video, image folder, take) to events, into a take.

The command lives with the simulator and reaches the `rigd` CLI through the `rigd.commands`
entry points, the same plugin path the `sim://` backends take: runtime rigd code never
imports `firmware_sim`.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from rigd.core.errors import RigdError

log = logging.getLogger(__name__)

#: --noise names -> (PixelModelConfig field, default value when given without "=value").
NOISE_TERMS: dict[str, tuple[str, float]] = {
    "leak": ("leak_rate_hz", 0.1),
    "shot": ("shot_noise_rate_hz", 0.1),
    "hot": ("hot_pixel_fraction", 1e-4),
    "hot_rate": ("hot_pixel_rate_hz", 100.0),
    "refractory": ("refractory_us", 100.0),
    "lowpass": ("lowpass_cutoff_hz", 300.0),
}


def parse_noise(spec: str | None) -> dict[str, Any]:
    """`leak,shot=0.5,hot=1e-4` -> PixelModelConfig fields; unknown names are an error."""
    fields: dict[str, Any] = {}
    if not spec:
        return fields
    for item in spec.split(","):
        item = item.strip()
        if not item:
            continue
        name, _, value = item.partition("=")
        name = name.strip().lower()
        if name not in NOISE_TERMS:
            raise typer.BadParameter(
                f"unknown noise term {name!r}; known: {', '.join(NOISE_TERMS)} (each optionally =value)",
                param_hint="--noise",
            )
        field, default = NOISE_TERMS[name]
        try:
            v = float(value) if value else default
        except ValueError:
            raise typer.BadParameter(f"{item!r}: {value!r} is not a number", param_hint="--noise") from None
        if field == "lowpass_cutoff_hz":
            fields["lowpass"] = True
        fields[field] = int(v) if field == "refractory_us" else v
    return fields


def simulate_events(
    input_path: Annotated[
        Path, typer.Argument(metavar="INPUT", help="Video file, image folder, or take (.h5) with RGB frames.")
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="Take (.h5) or EVT3 RAW (.raw) to create.")],
    fps: Annotated[
        float | None, typer.Option("--fps", help="Input frame rate (required for image folders).")
    ] = None,
    threshold: Annotated[float, typer.Option("--threshold", help="Contrast threshold C (log units).")] = 0.3,
    sigma: Annotated[float, typer.Option("--sigma", help="Per-pixel threshold mismatch std.")] = 0.0,
    seed: Annotated[int, typer.Option("--seed", help="Seed of all random draws.")] = 0,
    noise: Annotated[
        str | None,
        typer.Option(
            "--noise", help="Comma list of leak, shot, hot, hot_rate, refractory, lowpass, each [=value]."
        ),
    ] = None,
    substeps: Annotated[
        int | None, typer.Option("--substeps", help="Fixed sub-steps per frame pair (flow interpolation).")
    ] = None,
    max_px_per_step: Annotated[
        float | None,
        typer.Option("--max-px-per-step", help="Adaptive: max motion per sub-step, px (default 1)."),
    ] = None,
    max_substeps: Annotated[int, typer.Option("--max-substeps", help="Cap of adaptive sub-steps.")] = 64,
    width: Annotated[int | None, typer.Option("--width", help="Resize frames to this width.")] = None,
    height: Annotated[int | None, typer.Option("--height", help="Resize frames to this height.")] = None,
    camera: Annotated[str | None, typer.Option("--camera", help="Camera of a take input.")] = None,
    with_frames: Annotated[bool, typer.Option("--with-frames", help="Also store the frames.")] = False,
) -> None:
    """Simulate an event camera watching INPUT and write the events to a take."""
    # Here, not at the top: `rigd --help` loads this module and must not pay for numba and OpenCV.
    from firmware_sim.event_model import PixelModelConfig
    from firmware_sim.frame_sources import open_source
    from firmware_sim.frames_to_events import FramesToEvents, simulate_to_raw, simulate_to_take

    console = Console(stderr=True, soft_wrap=True)  # a path in a message stays whole off a terminal
    if substeps is not None and max_px_per_step is not None:
        raise typer.BadParameter("give --substeps or --max-px-per-step, not both")
    try:
        config = PixelModelConfig(threshold=threshold, sigma=sigma, seed=seed, **parse_noise(noise))
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    try:
        source = open_source(input_path, fps=fps, camera=camera)
    except (ValueError, OSError, RigdError) as exc:  # a take that cannot be read: TakeFormatError
        console.print(f"[bold red]error:[/] {exc}")
        raise typer.Exit(code=2) from exc
    described = _describe(source.description, input_path, camera)
    console.print(f"input: {described}", soft_wrap=True, highlight=False)
    try:
        size = _size(source, width, height)
        f2e = FramesToEvents(
            size[0],
            size[1],
            config,
            substeps=substeps,
            max_px_per_step=max_px_per_step,
            max_substeps=max_substeps,
        )
    except (ValueError, StopIteration, RigdError) as exc:
        source.close()
        console.print(f"[bold red]error:[/] {source.description}: {exc}")
        raise typer.Exit(code=2) from exc
    columns = (
        TextColumn("[progress.description]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[events]} events, {task.fields[sub]} sub-steps"),
        TimeRemainingColumn(),
    )
    with Progress(*columns, console=console, transient=False) as progress:
        task = progress.add_task("simulating", total=source.n_frames, events=0, sub=0)
        counts = {"events": 0}

        def on_step(res: Any) -> None:
            counts["events"] += len(res.events)
            progress.update(task, advance=1, events=counts["events"], sub=res.n_substeps)

        try:
            if out.suffix.lower() == ".raw":
                if with_frames:
                    raise ValueError("--with-frames needs a take (.h5) output, not .raw")
                summary = simulate_to_raw(source, out, f2e, on_step=on_step)
            else:
                summary = simulate_to_take(source, out, f2e, with_frames=with_frames, on_step=on_step)
        except (ValueError, OSError, RigdError) as exc:
            console.print(f"[bold red]error:[/] {exc}")
            raise typer.Exit(code=2) from exc
    mean_sub = summary.substeps_total / max(summary.frames - 1, 1)
    console.print(
        f"{summary.frames} frames -> {summary.events} events in {summary.path} "
        f"({summary.wall_s:.1f} s; sub-steps mean {mean_sub:.1f}, max {summary.substeps_max})",
        soft_wrap=True,
        highlight=False,
    )
    if f2e.capped_steps:
        steps = max(summary.frames - 1, 1)
        bound = f2e.max_px_per_step or 1.0
        console.print(
            f"[yellow]warning:[/] {f2e.capped_steps} of {steps} frame steps hit the sub-step cap "
            f"(--max-substeps {f2e.max_substeps}; up to {f2e.capped_motion_px:.0f} px of motion per frame, "
            f"{bound:g} px per sub-step asked): their events are coarser in time than asked. Raise "
            f"--max-substeps to {math.ceil(f2e.capped_motion_px / bound)}, or give a higher --fps or "
            "smaller frames (--width) if the motion is real.",
            soft_wrap=True,
            highlight=False,
        )


def _describe(description: str, input_path: Path, camera: str | None) -> str:
    """What is read; for a take without --camera, which camera that is and how to pick another."""
    if camera is not None or input_path.suffix.lower() not in (".h5", ".hdf5"):
        return description
    from rigd.take.reader import Take

    with Take(input_path) as take:
        cams = take.cameras
    if len(cams) < 2:
        return description
    return f"{description} (the first of {', '.join(cams)}; --camera picks another)"


def _size(source: Any, width: int | None, height: int | None) -> tuple[int, int]:
    """Output geometry: the requested one, the other side scaled to keep the aspect ratio."""
    if source.size is None:
        # Peek at the first frame and put it back in front of the stream.
        first = next(source.frames)
        h0, w0 = first[0].shape[:2]
        source.frames = _chain(first, source.frames)
    else:
        w0, h0 = source.size
    if width is None and height is None:
        return int(w0), int(h0)
    if width is not None and height is not None:
        return width, height
    if width is not None:
        return width, max(1, round(h0 * width / w0))
    assert height is not None
    return max(1, round(w0 * height / h0)), height


def _chain(first: Any, rest: Any) -> Any:
    yield first
    yield from rest
