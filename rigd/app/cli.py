"""The `rigd` command line."""

from __future__ import annotations

import logging
import signal
import sys
from collections.abc import Callable
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import typer

from rigd import __version__
from rigd.app.commands.calibrate import calibrate_app
from rigd.app.commands.consoles import fail, stderr_console, stdout_console
from rigd.app.commands.devices import devices
from rigd.app.commands.doctor import doctor
from rigd.app.commands.export import export
from rigd.app.commands.guided import guided
from rigd.app.commands.help import RigdTyper
from rigd.app.commands.progress import StageProgress
from rigd.app.commands.reconstruct import reconstruct
from rigd.app.commands.recover import recover_command
from rigd.app.commands.service import (
    ConnectOpt,
    capture_via_daemon,
    console_url,
    find_for_command,
    serve,
    status,
    stop,
)
from rigd.app.commands.takes import takes
from rigd.app.config import RigConfig, default_sim_rig, with_sim_scene
from rigd.core.errors import ConfigError, RigdError

if TYPE_CHECKING:
    from rigd.app.capture import Progress as CaptureProgress
    from rigd.app.service.client import DaemonClient
    from rigd.take.reader import TakeSummary

app = RigdTyper(
    help="Capture daemon for a hybrid RGB + event-camera rig.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)
log = logging.getLogger(__name__)
console = stderr_console()
out = stdout_console()


@app.callback()
def _main(
    verbose: Annotated[int, typer.Option("--verbose", "-v", count=True, help="More log output.")] = 0,
    log_level: Annotated[
        str | None,
        typer.Option(
            "--log-level", envvar="RIGD_LOG_LEVEL", help="debug, info, warning, error (overrides -v)."
        ),
    ] = None,
    log_format: Annotated[
        str,
        typer.Option("--log-format", envvar="RIGD_LOG_FORMAT", help="text, or json (one object per line)."),
    ] = "text",
    log_file: Annotated[
        Path | None, typer.Option("--log-file", envvar="RIGD_LOG_FILE", help="Also log to this file.")
    ] = None,
) -> None:
    from rigd.app.logs import setup_logging

    level = logging.WARNING - 10 * min(verbose, 2)
    if log_level is not None:
        named = logging.getLevelNamesMapping().get(log_level.upper())
        if named is None:
            raise fail(ConfigError(f"--log-level: unknown level {log_level!r} (debug, info, warning, error)"))
        level = named
    if log_format not in ("text", "json"):
        raise fail(ConfigError(f"--log-format: {log_format!r} is not text or json"))
    setup_logging(level, "json" if log_format == "json" else "text", log_file)


#: Signals that end an in-process take cleanly (drained and finalized), as Ctrl-C does.
_STOPS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
#: Exit code of `capture --strict` / `inspect --strict` for a take that is not complete
#: (degraded: it lost data; docs/take-format.md, *Verdict*).
STRICT_EXIT = 3

StrictOpt = Annotated[
    bool,
    typer.Option(
        "--strict",
        help=f"Exit {STRICT_EXIT} unless the take's verdict is complete (nothing lost: no loss record, "
        "missing pulse, dropped frame or silent device).",
    ),
]


@app.command()
def capture(
    config: Annotated[
        Path | None, typer.Option("--config", "-c", help="Rig config (TOML/JSON/YAML); default: the sim rig.")
    ] = None,
    duration: Annotated[
        float | None,
        typer.Option("--duration", "-d", help="Seconds of trigger pulses (default 5; a replay: all of it)."),
    ] = None,
    out_dir: Annotated[
        Path | None, typer.Option("--out", "-o", help="Directory for the take (default: takes).")
    ] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print the summary as JSON.")] = False,
    label: Annotated[str | None, typer.Option("--label", help="Word for the take's file name.")] = None,
    connect: ConnectOpt = None,
    local: Annotated[
        bool, typer.Option("--local", help="Capture in this process even if a daemon is running.")
    ] = False,
    replay: Annotated[
        Path | None,
        typer.Option("--replay", help="Replay a recorded take as the rig (replay:// devices, in-process)."),
    ] = None,
    sim_clock: Annotated[
        str,
        typer.Option(
            "--sim-clock",
            help="real, or virtual: the sim or replayed rig runs as fast as the CPU allows, "
            "the same take for the same seed.",
        ),
    ] = "real",
    strict: StrictOpt = False,
    scene: Annotated[
        str | None,
        typer.Option(
            "--scene",
            help="Sim rigs: what every sim camera and event sensor films, sprites or board (the "
            "moving calibration chessboard: a take to calibrate the rig from). In-process.",
        ),
    ] = None,
) -> None:
    """Capture one take: through the running daemon if there is one, else in-process
    (with no --config, from the built-in simulated rig)."""
    from rigd.app.capture import new_take_path, run_capture
    from rigd.app.capture.request import check_duration, check_out_dir
    from rigd.app.inspect import summarize

    if sim_clock not in ("real", "virtual"):
        raise fail(ConfigError(f"--sim-clock {sim_clock!r}: use real or virtual"))
    try:  # before a daemon is asked, a device opened or a file made
        if duration is not None:
            check_duration(duration, "--duration")
        if out_dir is not None:
            check_out_dir(out_dir, "--out")
    except RigdError as exc:
        raise fail(exc) from exc
    if replay is not None and config is not None:
        raise fail(ConfigError("--replay plays a take's own rig: drop --config"))
    if replay is not None and scene is not None:
        raise fail(ConfigError("--replay plays what the take recorded: drop --scene"))
    if sim_clock == "virtual" and config is not None:
        raise fail(
            ConfigError(
                "--sim-clock applies to the built-in sim rig and --replay; in a config, give every "
                "sim:// spec clock=virtual"
            )
        )
    try:
        in_process = replay is not None or sim_clock == "virtual" or scene is not None
        client = None if in_process else find_for_command(connect, local)
    except RigdError as exc:
        raise fail(exc) from exc
    if client is not None:
        with client:
            if config is not None or out_dir is not None:
                raise fail(
                    ConfigError(
                        f"a rigd daemon runs at {client.endpoint} with its own rig config and take dir; "
                        "drop --config/--out to capture through it, or pass --local to capture in-process"
                    )
                )
            last = _capture_remote(client, 5.0 if duration is None else duration, label, json_out)
        if strict:
            _check_strict(last["path"], last.get("verdict"), last.get("verdict_reasons") or [])
        return
    out_dir = out_dir or Path("takes")
    clock: Literal["real", "virtual"] = "virtual" if sim_clock == "virtual" else "real"
    try:
        if replay is not None:
            from rigd.app.replay import replay_config

            rig, recorded_s = replay_config(replay, clock=clock)
            duration = recorded_s if duration is None else duration
        else:
            rig = RigConfig.load(config) if config else default_sim_rig(clock=clock)
            if scene is not None:
                rig = with_sim_scene(rig, scene)
        rig.check_devices()
    except RigdError as exc:
        raise fail(exc) from exc
    duration = 5.0 if duration is None else duration
    with StageProgress(console, "capture", quiet=json_out) as bar:
        on_progress = _capture_progress(bar)
        path = new_take_path(out_dir, rig.name, label)
        try:
            result = run_capture(
                rig, out_dir, duration, on_progress=on_progress, path=path, stop_signals=_STOPS
            )
        except RigdError as exc:
            raise fail(exc) from exc
        except KeyboardInterrupt:  # a second signal while finalizing: the take is left as it is
            console.print(
                f"[bold red]aborted:[/] take {path} left unfinished; `rigd recover {path}` seals it",
                soft_wrap=True,
            )
            raise typer.Exit(code=130) from None
    summary = summarize(result.path)
    if json_out:
        out.print_json(summary.model_dump_json())
    else:
        # The verdict first: whether the take kept everything is what the operator reads first.
        _print_summary(summary, take_line=f"take: {result.path}")
        out.print(
            f"wrote {result.bytes_written / 1e6:.1f} MB in {result.wall_s:.1f} s "
            f"({result.bytes_written / 1e6 / max(result.wall_s, 1e-9):.1f} MB/s)"
        )
    if result.stop_signal is not None:
        name = signal.Signals(result.stop_signal).name
        console.print(f"stopped by {name}: take {result.path} was finalized", soft_wrap=True)
        raise typer.Exit(code=128 + result.stop_signal)
    if strict:
        _check_strict(str(result.path), summary.verdict, summary.verdict_reasons)


def _check_strict(path: str, verdict: str | None, reasons: list[str]) -> None:
    """`--strict`: one line and exit STRICT_EXIT unless the take holds everything."""
    if verdict == "complete":
        return
    from rigd.take.verdict import TakeVerdict

    why = (
        "unknown (the daemon did not say)"
        if verdict is None
        else TakeVerdict.model_validate({"verdict": verdict, "reasons": reasons}).line(
            limit=len(reasons) or 1
        )
    )
    console.print(
        f"--strict: take {path} is not complete: {why}", soft_wrap=True, markup=False, highlight=False
    )
    raise typer.Exit(code=STRICT_EXIT)


#: What each phase of an in-process capture counts, and what it is doing (rigd.app.capture.results).
_CAPTURE_PHASES: dict[str, tuple[str, str]] = {
    "capturing": ("pulses", ""),
    "waiting for devices": ("devices", "each device delivering up to the take's last pulse"),
    "draining": ("queued items", "the writer writing what is still queued"),
    "finalizing": ("", "fitting the device clocks and sealing the take"),
}


def _capture_progress(bar: StageProgress) -> Callable[[CaptureProgress], None]:
    """The capture's progress callback: a new stage for every phase the take entered (the pulses
    are out long before the take is written), the current phase's count and the events so far."""
    shown = 0

    def on_progress(p: CaptureProgress) -> None:
        nonlocal shown
        for phase in p.phases[shown:]:
            unit, note = _CAPTURE_PHASES[phase]
            bar.stage(phase, p.phase_total if phase == p.phase else None, unit, note)
        shown = len(p.phases)
        events = sum(p.events.values())
        note = _CAPTURE_PHASES[p.phase][1]
        numbers = f"{events / 1e6:.1f} Mev written  queue {p.queue_depth}"
        bar.advance_to(p.phase_done, f"{note}; {numbers}" if note else numbers, p.phase_total)

    return on_progress


def _capture_remote(
    client: DaemonClient, duration: float, label: str | None, json_out: bool
) -> dict[str, Any]:
    """Follow a daemon's take: seconds of pulses against the duration asked for, then its stopping
    (draining, fitting the clocks, sealing), then the summary an in-process capture prints; the
    daemon's summary of the take."""
    taken: list[str] = []
    with StageProgress(console, "capture (daemon)", quiet=json_out) as bar:
        shown: list[str] = []

        def on_status(t: dict[str, Any]) -> None:
            state = t.get("state")
            if t.get("take") and not taken:
                taken.append(t["take"])
            if not taken or t.get("take") != taken[0]:
                return  # before the take shows up, or after it ended
            if state == "capturing" and not shown:
                bar.stage("capturing", max(1, round(duration)), "s of pulses")
                shown.append("capturing")
            elif state == "stopping" and "stopping" not in shown:
                note = "the daemon drains its queue, fits the device clocks and seals the take"
                bar.stage("stopping", None, "", note)
                shown.append("stopping")
            faults = t.get("faults") or []
            detail = f"{t.get('pulses') or 0:,} pulses  queue {t.get('queue_depth')}"
            detail += f"  faults: {len(faults)}" if faults else ""
            elapsed = min(round(t.get("take_elapsed_s") or 0.0), max(1, round(duration)))
            done = elapsed if state == "capturing" else None
            bar.advance_to(done, detail)

        last = capture_via_daemon(client, duration, label, json_out, on_status)
    if not json_out and taken:
        _print_daemon_take(client, taken[0])
    return last


def _print_daemon_take(client: DaemonClient, path: str) -> None:
    """The summary an in-process capture prints, for a take the daemon wrote: read from the file
    (the daemon answers on a local socket, so its take is on this host), with the daemon's count of
    bytes written."""
    from rigd.app.inspect import summarize
    from rigd.app.service.client import DaemonUnavailableError

    try:
        last = client.call("status").get("last_take") or {}
    except DaemonUnavailableError:  # gone since the take ended: the file still has the summary
        last = {}
    try:
        summary = summarize(Path(path))
    except (OSError, RigdError) as exc:
        console.print(f"no summary: cannot read {path} here ({exc}); `rigd inspect` it where it is")
        return
    _print_summary(summary)
    if last.get("path") == path and last.get("bytes_written"):
        out.print(f"wrote {last['bytes_written'] / 1e6:.1f} MB")


@app.command()
def inspect(
    take: Annotated[Path, typer.Argument(help="Take file (.h5).")],
    json_out: Annotated[bool, typer.Option("--json", help="Machine-readable summary.")] = False,
    thumbnails: Annotated[
        Path | None, typer.Option("--thumbnails", help="Write a contact sheet of frames and event images.")
    ] = None,
    strict: StrictOpt = False,
) -> None:
    """Validate a take against the schema and print its summary, its verdict first."""
    from rigd.app.inspect import status_hint, summarize, write_thumbnails

    if not take.exists():
        raise fail(FileNotFoundError(f"no such take: {take}"))
    try:
        summary = summarize(take)
        hint = status_hint(summary)
        if thumbnails is not None:
            write_thumbnails(take, thumbnails)
    except RigdError as exc:
        raise fail(exc) from exc
    if json_out:
        out.print_json(summary.model_dump_json())
    else:
        _print_summary(summary)
        if thumbnails is not None:
            out.print(f"thumbnails: {thumbnails}")
    if hint is not None:  # a take that is not complete is not usable as it is
        console.print(hint, soft_wrap=True)
    if summary.problems or hint is not None:
        raise typer.Exit(code=1)
    if strict:
        _check_strict(str(take), summary.verdict, summary.verdict_reasons)


@app.command("convert")
def convert_cmd(
    src: Annotated[Path, typer.Argument(help="Input: .raw/.dat recording or .h5 take.")],
    dst: Annotated[Path, typer.Argument(help="Output: .h5 take or .raw/.dat recording.")],
    sensor: Annotated[str | None, typer.Option("--sensor", help="Event sensor name in the take.")] = None,
    fmt: Annotated[
        str, typer.Option("--format", help="EVT format of a .raw output: evt3, evt2, evt21.")
    ] = "evt3",
    strict: Annotated[bool, typer.Option("--strict", help="Stop at the first invalid word.")] = False,
) -> None:
    """Convert a RAW/DAT recording to a take, or a take's event sensor to RAW/DAT."""
    from rigd.app.convert import convert

    if not src.exists():
        raise fail(FileNotFoundError(f"no such file: {src}"))
    with StageProgress(console, "convert") as bar:
        bar.stage("converting", _events_in(src, sensor), "events", f"{src.name} -> {dst.name}")
        try:
            n = convert(src, dst, sensor=sensor, fmt=fmt, strict=strict, on_progress=bar.advance_to)
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
            return take.event_count(name) if name in names else None
    except (OSError, RigdError):
        return None  # convert says what is wrong with the file


@app.command("default-config")
def default_config() -> None:
    """Print the built-in simulated rig config, a starting point for a real one."""
    out.print_json(default_sim_rig().model_dump_json())


@app.command()
def version() -> None:
    """Print the rigd version."""
    out.print(__version__)


def _add_plugin_commands() -> None:
    """Commands other packages contribute through the `rigd.commands` entry points (the
    simulator's `simulate-events`), loaded without importing those packages by name."""
    for ep in metadata.entry_points(group="rigd.commands"):
        try:
            command = ep.load()
        except ImportError as exc:
            log.warning("command %s unavailable: %s", ep.name, exc)
            continue
        app.command(ep.name)(command)


def _print_summary(summary: TakeSummary, take_line: str | None = None) -> None:
    """The summary, its verdict line first; `take_line` (the take's path) goes right after it."""
    from rigd.app.inspect import summary_renderables

    parts = summary_renderables(summary)
    if take_line is not None:
        out.print(parts[0], soft_wrap=True, highlight=False)
        typer.echo(take_line)
        parts = parts[1:]
    for part in parts:
        out.print(part, soft_wrap=isinstance(part, str), highlight=False)


_add_plugin_commands()
calibrate_app.command("guided")(guided)
app.add_typer(calibrate_app, name="calibrate", help="Calibrate cameras and event sensors.")
app.command("reconstruct")(reconstruct)
app.command("export")(export)
app.command("devices")(devices)
app.command("doctor")(doctor)
app.command("serve")(serve)
app.command("recover")(recover_command)
app.command("takes")(takes)
app.command("status")(status)
app.command("console-url")(console_url)
app.command("stop")(stop)


def main() -> None:
    try:
        app()
    except KeyboardInterrupt:
        console.print("interrupted")
        sys.exit(130)


if __name__ == "__main__":
    main()
