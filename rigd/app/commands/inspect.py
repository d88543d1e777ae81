"""`rigd inspect` and `rigd convert`: a take's summary and verdict; RAW/DAT <-> take."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from rigd.app.commands.consoles import fail, stderr_console, stdout_console
from rigd.app.commands.progress import StageProgress
from rigd.app.commands.summaries import StrictOpt, check_strict, print_summary
from rigd.core.errors import RigdError, TakeFormatError, TakeInUseError

console = stderr_console()
out = stdout_console()


def inspect(
    take: Annotated[Path, typer.Argument(help="Take file (.h5).")],
    json_out: Annotated[bool, typer.Option("--json", help="Machine-readable summary.")] = False,
    thumbnails: Annotated[
        Path | None, typer.Option("--thumbnails", help="Write a contact sheet of frames and event images.")
    ] = None,
    strict: StrictOpt = False,
) -> None:
    """Validate a take against the schema and print its summary, its verdict first."""
    from rigd.products.inspect import status_hint, summarize, write_thumbnails

    if not take.exists():
        raise fail(FileNotFoundError(f"no such take: {take}"))
    try:
        summary = summarize(take)
        hint = status_hint(summary)
        if thumbnails is not None:
            write_thumbnails(take, thumbnails)
    except TakeInUseError as exc:
        raise fail(exc) from exc
    except TakeFormatError as exc:  # the verdict first, as for any take; then the error (exit 2)
        from rigd.take.verdict import damaged_verdict

        line = damaged_verdict([str(exc)]).line()
        head, sep, rest = line.partition(" — ")
        out.print(f"[bold red]verdict: {escape(head)}[/]{sep}{escape(rest)}", soft_wrap=True, highlight=False)
        raise fail(exc) from exc
    except RigdError as exc:
        raise fail(exc) from exc
    if json_out:
        out.print_json(summary.model_dump_json())
    else:
        print_summary(summary)
        if thumbnails is not None:
            out.print(f"thumbnails: {thumbnails}")
    if hint is not None:  # a take that is not complete is not usable as it is
        console.print(hint, soft_wrap=True)
    if summary.problems or hint is not None:
        raise typer.Exit(code=1)
    if strict:
        check_strict(str(take), summary.verdict, summary.verdict_reasons)


def convert_cmd(
    src: Annotated[
        Path,
        typer.Argument(
            help="Input: .raw/.dat recording, rosbag2 bag (.db3, .mcap, bag directory) or .h5 take."
        ),
    ],
    dst: Annotated[Path, typer.Argument(help="Output: .h5 take or .raw/.dat recording.")],
    sensor: Annotated[str | None, typer.Option("--sensor", help="Event sensor name in the take.")] = None,
    fmt: Annotated[
        str,
        typer.Option(
            "--format",
            help="EVT format of a .raw output: evt3, evt2, evt21 (IMX636 half-swapped words, "
            "endianness=legacy) or evt21_le (little-endian words).",
        ),
    ] = "evt3",
    strict: Annotated[bool, typer.Option("--strict", help="Stop at the first invalid word.")] = False,
    no_triggers: Annotated[
        bool,
        typer.Option(
            "--no-triggers",
            help="A .raw/.dat output without the trigger edges (readers such as expelliarmus stop at them).",
        ),
    ] = False,
) -> None:
    """Convert a RAW/DAT recording or a rosbag2 bag to a take, or a take's event sensor to RAW/DAT."""
    from rigd.products.convert import convert

    if not src.exists():
        raise fail(FileNotFoundError(f"no such file: {src}"))
    with StageProgress(console, "convert") as bar:
        bar.stage("converting", _events_in(src, sensor), "events", f"{src.name} -> {dst.name}")
        try:
            n = convert(
                src,
                dst,
                sensor=sensor,
                fmt=fmt,
                strict=strict,
                triggers=not no_triggers,
                on_progress=bar.advance_to,
            )
        except RigdError as exc:
            raise fail(exc) from exc
    out.print(f"{dst}: {n:,} events")


def _events_in(src: Path, sensor: str | None) -> int | None:
    """Events a conversion will write, when known up front: a take's sensor count (a RAW or DAT
    recording is only counted by decoding it, so its bar shows the count and the time so far)."""
    if src.suffix.lower() not in (".h5", ".hdf5"):
        return None
    from rigd.take.reader import Take

    try:
        with Take(src) as take:
            names = take.event_sensors
            name = sensor if sensor is not None else (names[0] if len(names) == 1 else None)
            return take.sensor(name).count if name in names else None
    except (OSError, RigdError):
        return None  # convert says what is wrong with the file
