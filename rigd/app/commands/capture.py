"""`rigd capture`: one take, through the running daemon if there is one, else in-process."""

from __future__ import annotations

import signal
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from rigd.app.commands.consoles import fail, stderr_console, stdout_console
from rigd.app.commands.flags import sim_clock_flag
from rigd.app.commands.progress import StageProgress
from rigd.app.commands.service import ConnectOpt, capture_via_daemon, find_for_command
from rigd.app.commands.summaries import StrictOpt, check_strict, print_summary
from rigd.app.config import RigConfig, default_sim_rig, with_sim_scene
from rigd.core.errors import ConfigError, RigdError

if TYPE_CHECKING:
    from rigd.app.capture import Progress as CaptureProgress
    from rigd.app.service.client import DaemonClient

console = stderr_console()
out = stdout_console()

#: Signals that end an in-process take cleanly (drained and finalized), as Ctrl-C does.
_STOPS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


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
    _refuse_bad_flags(config, duration, out_dir, replay, sim_clock, scene)
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
            check_strict(last["path"], last.get("verdict"), last.get("verdict_reasons") or [])
        return
    clock = sim_clock_flag(sim_clock, config, "the built-in sim rig and --replay")
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
    _warm_up_if_cold()
    _capture_in_process(
        rig, out_dir or Path("takes"), 5.0 if duration is None else duration, label, json_out, strict
    )


def _warm_up_if_cold() -> None:
    """On a cold numba cache (a fresh install, a new NUMBA_CACHE_DIR), `rigd warmup` first: a
    kernel compiled during the take holds the GIL for seconds while the sensors' data piles up."""
    from rigd.app.commands.warmup import run_warmup
    from rigd.app.warmup import is_warm

    if not is_warm():
        run_warmup(
            "numba's cache lacks the capture path's kernels; compiling them before the take", required=False
        )


def _refuse_bad_flags(
    config: Path | None,
    duration: float | None,
    out_dir: Path | None,
    replay: Path | None,
    sim_clock: str,
    scene: str | None,
) -> None:
    """Flags that cannot go together, or values out of range, refused before a daemon is asked,
    a device opened or a file made."""
    from rigd.app.capture.request import check_duration, check_out_dir

    sim_clock_flag(sim_clock, config, "the built-in sim rig and --replay")
    try:
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


def _capture_in_process(
    rig: RigConfig, out_dir: Path, duration: float, label: str | None, json_out: bool, strict: bool
) -> None:
    """Run the take here, with a progress bar; print its summary, verdict first."""
    from rigd.app.capture import new_take_path, run_capture
    from rigd.products.inspect import summarize

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
        print_summary(summary, take_line=f"take: {result.path}")
        out.print(
            f"wrote {result.bytes_written / 1e6:.1f} MB in {result.wall_s:.1f} s "
            f"({result.bytes_written / 1e6 / max(result.wall_s, 1e-9):.1f} MB/s)"
        )
    if result.stop_signal is not None:
        name = signal.Signals(result.stop_signal).name
        console.print(f"stopped by {name}: take {result.path} was finalized", soft_wrap=True)
        raise typer.Exit(code=128 + result.stop_signal)
    if strict:
        check_strict(str(result.path), summary.verdict, summary.verdict_reasons)


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
            # a phase already over when first seen shows the count it started from
            bar.stage(phase, p.phase_total if phase == p.phase else p.entered_with.get(phase), unit, note)
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
    from rigd.app.service.client import DaemonUnavailableError
    from rigd.products.inspect import summarize

    try:
        last = client.call("status").get("last_take") or {}
    except DaemonUnavailableError:  # gone since the take ended: the file still has the summary
        last = {}
    try:
        summary = summarize(Path(path))
    except (OSError, RigdError) as exc:
        console.print(f"no summary: cannot read {path} here ({exc}); `rigd inspect` it where it is")
        return
    print_summary(summary)
    if last.get("path") == path and last.get("bytes_written"):
        out.print(f"wrote {last['bytes_written'] / 1e6:.1f} MB")
