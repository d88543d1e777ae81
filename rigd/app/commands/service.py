"""`rigd serve`, `rigd status`, `rigd stop`, `rigd console-url`, and the daemon side of `rigd capture`.

Commands that act on the rig talk to a running daemon when one answers at the control
endpoint; `capture` and `devices` fall back to doing the work in-process when none does.
Exit codes: 0 done, 1 the take ended with an error (for `serve`: its control loop failed, the
take was finalized; systemd restarts it), 2 bad input / request refused, 3 no daemon running
(status, stop), or the daemon stopped answering during `capture`.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich import box
from rich.console import Console
from rich.table import Table

from rigd.app.commands.consoles import fail, stderr_console, stdout_console
from rigd.app.config import RigConfig, default_control_endpoint, default_sim_rig
from rigd.core.errors import ConfigError, RigdError

if TYPE_CHECKING:  # ZeroMQ loads when a command talks to the daemon, not for `--help`
    from rigd.app.service.client import DaemonClient, DaemonUnavailableError

log = logging.getLogger(__name__)
_err = stderr_console()

#: Exit code of `rigd capture` when the daemon stops answering before the take is over.
DAEMON_LOST_EXIT = 3

#: Exit code of `rigd serve` when its control loop failed (the take was finalized): not 2,
#: which the systemd unit does not restart (RestartPreventExitStatus=2, for config errors).
CONTROL_PLANE_FAILED_EXIT = 1

#: How long `capture` waits for the daemon to open the devices and start the trigger.
CAPTURE_START_TIMEOUT_S = 120.0

ConnectOpt = Annotated[
    str | None,
    typer.Option(
        "--connect", help="Daemon control endpoint; default: the local IPC socket (see docs/service.md)."
    ),
]


def control_endpoint(connect: str | None) -> str:
    return connect or default_control_endpoint()


def _require_daemon(connect: str | None, hint: str) -> DaemonClient:
    """The daemon at the endpoint, or exit 3 saying there is none."""
    from rigd.app.service.client import find_daemon

    endpoint = control_endpoint(connect)
    try:
        client = find_daemon(endpoint)
    except RigdError as exc:  # another user's daemon, or one that refused the ping
        raise fail(exc) from exc
    if client is None:
        _err.print(f"no rigd daemon at {endpoint}{hint}")
        raise typer.Exit(code=3)
    return client


def read_token_file(path: Path) -> str:
    """The console token kept in `path` (surrounding whitespace dropped); ConfigError naming the
    file when it cannot be read or is empty."""
    try:
        token = path.read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"--http-token-file {path}: cannot be read: {exc}") from exc
    if not token:
        raise ConfigError(f"--http-token-file {path}: is empty")
    return token


def serve(
    config: Annotated[
        Path | None, typer.Option("--config", "-c", help="Rig config (TOML/JSON/YAML); default: the sim rig.")
    ] = None,
    take_dir: Annotated[Path | None, typer.Option("--take-dir", help="Overrides service.take_dir.")] = None,
    control: Annotated[str | None, typer.Option("--control", help="Overrides service.control.")] = None,
    telemetry: Annotated[str | None, typer.Option("--telemetry", help="Overrides service.telemetry.")] = None,
    metrics_port: Annotated[
        int | None, typer.Option("--metrics-port", help="Prometheus port (0: any free port; -1: off).")
    ] = None,
    http: Annotated[
        str, typer.Option("--http", help="Web console address HOST:PORT (beyond loopback: needs a token).")
    ] = "127.0.0.1:8750",
    no_http: Annotated[bool, typer.Option("--no-http", help="No web console.")] = False,
    http_token_file: Annotated[
        Path | None,
        typer.Option(
            "--http-token-file",
            help="File holding the console token (required beyond loopback; or RIGD_HTTP_TOKEN). "
            "Never on the command line: every user's `ps` shows a process's arguments.",
        ),
    ] = None,
    http_token: Annotated[
        str | None, typer.Option("--http-token", hidden=True, help="Refused: use --http-token-file.")
    ] = None,
    host: Annotated[
        str | None, typer.Option("--host", help="This daemon's host on a multi-host rig (service.host).")
    ] = None,
) -> None:
    """Run the capture daemon: control socket, telemetry, metrics, web console; Ctrl-C/SIGTERM to stop."""
    from rigd.app.service.daemon import Attachment, ControlPlaneError, run_daemon

    if http_token is not None:  # already in this process's arguments for all to see: refused
        raise fail(
            "--http-token puts the console's secret where every user's `ps` shows it; give it in a "
            "file only its owner reads (--http-token-file) or in RIGD_HTTP_TOKEN"
        )
    try:
        token = read_token_file(http_token_file) if http_token_file is not None else None
        rig = RigConfig.load(config) if config else default_sim_rig()
        overrides: dict[str, Any] = {}
        if take_dir is not None:
            overrides["take_dir"] = take_dir
        if control is not None:
            overrides["control"] = control
        if telemetry is not None:
            overrides["telemetry"] = telemetry
        if metrics_port is not None:
            overrides["metrics_port"] = None if metrics_port < 0 else metrics_port
        if host is not None:
            overrides["host"] = host
        if overrides:
            data = rig.model_dump(mode="json")
            data["service"].update({k: str(v) if isinstance(v, Path) else v for k, v in overrides.items()})
            rig = RigConfig.from_data(data, source=f"{config or 'sim rig'} + command line")
        rig.check_devices()
        attachments: list[Attachment] = []
        console = None
        if not no_http:
            from rigd.app.console.security import parse_bind
            from rigd.app.console.server import ConsoleServer

            host, port = parse_bind(http)
            console = ConsoleServer(host, port, token=token)  # refuses remote without a token
            attachments.append(console)
        attachments.append(Announcer(console))
        run_daemon(rig, attachments)
    except ControlPlaneError as exc:
        raise fail(exc, code=CONTROL_PLANE_FAILED_EXIT) from exc
    except RigdError as exc:
        raise fail(exc) from exc


class Announcer:
    """Says where the daemon listens once everything is bound, then `ready` (stdout, flushed).

    The console line is its login URL (it carries the secret, as Jupyter's does): stdout is the
    operator's terminal. When stdout is the systemd journal (`JOURNAL_STREAM`), which others may
    read (groups adm, systemd-journal), it is the bare address and a pointer to `rigd console-url`.
    """

    def __init__(self, console: Any = None) -> None:
        self.console = console

    def start(self, daemon: Any) -> None:
        svc = daemon.config.service
        lines = [f"control: {svc.control_endpoint}", f"telemetry: {svc.telemetry_endpoint}"]
        lines.append(f"metrics: {daemon.metrics_url or 'off'}")
        if self.console is None:
            lines.append("console: off")
        elif os.environ.get("JOURNAL_STREAM"):
            lines.append(f"console: {self.console.url} (login URL: rigd console-url)")
        else:
            lines.append(f"console: {self.console.login_url}")
        lines.append(f"takes: {svc.take_dir}")
        lines.append("ready")
        typer.echo("\n".join(lines))
        sys.stdout.flush()

    def close(self) -> None:
        """Nothing to release."""


def console_url(connect: ConnectOpt = None) -> None:
    """Print the web console's login URL (for the daemon's user only).

    The URL carries the console's secret, read from the daemon's owner-only runtime directory."""
    from rigd.app.console.login import NoConsoleLoginError, login_path, read_login

    path = login_path(control_endpoint(connect))
    try:
        login = read_login(path)
    except NoConsoleLoginError as exc:
        raise fail(exc, code=3) from exc
    except RigdError as exc:
        raise fail(exc) from exc
    typer.echo(login.login_url)


def status(
    connect: ConnectOpt = None,
    json_out: Annotated[bool, typer.Option("--json", help="The raw telemetry document.")] = False,
) -> None:
    """Show what the daemon is doing: state, devices, rates, losses, faults, disk."""
    with _require_daemon(connect, " (an in-process `rigd capture` is not visible here)") as client:
        try:
            t = client.call("status")
        except RigdError as exc:
            raise fail(exc) from exc
    if json_out:
        typer.echo(json.dumps(t, indent=2))
        return
    print_status(t, stdout_console())


def _flush_text(t: dict[str, Any]) -> str:
    age = t.get("last_flush_age_s")
    if age is None:
        return "  not flushed yet"
    return f"  flushed {age:.1f} s ago (longest {t.get('flush_max_s', 0.0) * 1e3:.0f} ms)"


def _headroom_text(t: dict[str, Any]) -> str:
    """The writer's load, and what the event sensors send against what it would hold."""
    busy = float(t.get("writer_busy", 0.0))
    events = sum(d["rate_hz"] for d in t["devices"] if d["kind"] == "event_sensor")
    line = (
        f"writer {busy * 100:.0f} % busy (headroom {100 - busy * 100:.0f} %)  events {events / 1e6:.2f} Mev/s"
    )
    cap = t.get("event_capacity_hz")
    if cap:
        line += f" of ~{cap / 1e6:.0f} Mev/s this host's writer holds"
    shed = sum(d.get("shed", 0) for d in t["devices"])
    if shed:
        line += f"  [bold red]shed {shed:,} events (overload)[/]"
    return line


#: Device kinds as the status table says them (short: the table fits 80 columns).
_KIND_WORDS = {"rgb_camera": "camera", "event_sensor": "events", "trigger": "trigger"}


def _count(n: float, small: str = "{:,.0f}") -> str:
    """A count or rate in at most 7 characters: 123,456, 1.23 M, 24.95 M (`--json` has the number)."""
    if abs(n) >= 1e6:
        return f"{n / 1e6:.2f} M"
    if abs(n) >= 1e5:
        return f"{n / 1e3:.1f} k"
    return small.format(n)


def print_status(t: dict[str, Any], out: Console) -> None:
    disk = f"{t['disk_free_bytes'] / 1e9:.1f} of {t['disk_total_bytes'] / 1e9:.1f} GB free"
    # takes_completed counts this daemon's takes since it started, not the files in take_dir
    # (`rigd takes` lists those).
    done = f"takes finalized since start: {t['takes_completed']}"
    out.print(f"state: [bold]{t['state']}[/]   {done}   disk: {disk}")
    if t.get("take"):
        out.print(
            f"take: {t['take']}  {t['take_elapsed_s']:.1f} s  pulses {t['pulses']}  "
            f"queue {t['queue_depth']}/{t['queue_capacity']}  {t['bytes_written'] / 1e6:.0f} MB"
            + _flush_text(t),
            soft_wrap=True,
        )
        out.print(_headroom_text(t), soft_wrap=True)
    headers = ("device", "kind", "state", "total", "rate/s", "lost", "queued", "reconn", "jitter µs")
    rows = []
    for d in t["devices"]:
        jitter = d.get("interval_jitter_us")
        rows.append(
            (
                d["name"],
                _KIND_WORDS.get(d["kind"], d["kind"]),
                d["state"],
                _count(d["total"]),
                _count(d["rate_hz"], "{:.1f}"),
                str(d["lost"]),
                str(d.get("queued", 0)),
                str(d.get("reconnects", 0)),
                "-" if jitter is None else f"{jitter:.2f}",
            )
        )
    # Every cell whole, on an 80-column terminal too (it once printed `trigg...`, `rgb_c...`): light
    # borders, short words, and no column narrower than its longest cell.
    table = Table(box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True)
    for i, head in enumerate(headers):
        widest = max([len(head), *(len(r[i]) for r in rows)])
        table.add_column(head, no_wrap=True, min_width=widest, justify="left" if i < 3 else "right")
    for row in rows:
        table.add_row(*row)
    out.print(table)
    for h in t.get("hosts", []):
        out.print(host_line(h), soft_wrap=True, highlight=False)
    for f in t.get("faults", []):
        out.print(
            f"[bold red]fault[/] {f['code']} {f.get('device') or ''}: {f['message']} (since {f['since_utc']})"
        )
    last = t.get("last_take")
    if last:
        out.print(
            f"last take: {last['path']} ({last['status']})"
            + (f": {last['error']}" if last.get("error") else "")
            + (f", {last['end_reason']}" if last.get("end_reason") else ""),
            soft_wrap=True,
        )
        out.print(f"  verdict: {verdict_text(last)}", soft_wrap=True, highlight=False, markup=False)


def host_line(h: dict[str, Any]) -> str:
    """Another host of a multi-host rig, as the coordinator last reached it."""
    devices = ", ".join(h.get("devices", [])) or "no devices"
    if not h.get("reachable"):
        return f"[bold red]host {h['name']}[/] ({h['endpoint']}): unreachable, {devices}: {h.get('message')}"
    line = f"host {h['name']} ({h['endpoint']}): {h.get('state')}, {devices}, pulses {h.get('pulses', 0)}"
    return line + (f"  [bold red]{h['message']}[/]" if h.get("message") else "")


def verdict_text(last: dict[str, Any]) -> str:
    """A daemon take's verdict and why (`rigd.take.verdict`); a daemon from before verdicts
    sends none, and its take's verdict is then unknown here (`rigd inspect` computes it)."""
    verdict = last.get("verdict")
    if verdict is None:
        return f"unknown (the daemon does not say; `rigd inspect {last['path']}` does)"
    from rigd.take.verdict import TakeVerdict

    return TakeVerdict(verdict=verdict, reasons=last.get("verdict_reasons") or []).line()


def stop(
    connect: ConnectOpt = None,
    wait: Annotated[bool, typer.Option("--wait/--no-wait", help="Wait until the take is finalized.")] = True,
) -> None:
    """Stop the daemon's running take (it is finalized, nothing is lost)."""
    with _require_daemon(connect, "; an in-process `rigd capture` stops with Ctrl-C") as client:
        try:
            res = client.call("stop", reason="rigd stop")
        except RigdError as exc:
            raise fail(exc) from exc
        if not wait:
            typer.echo(f"stopping {res['take']}")
            return
        last = wait_for_take(client, res["take"])
        typer.echo(f"stopped take {last['path']}")
        typer.echo(f"  {take_summary_line(last)}")
        if last.get("error"):
            raise fail(last["error"], code=1)


def take_summary_line(last: dict[str, Any]) -> str:
    """One line an operator reads: status, why it ended, frames, events, size, losses."""
    frames = sum(last.get("frames", {}).values())
    events = sum(last.get("events", {}).values())
    losses = last.get("losses", [])
    parts = [
        last.get("verdict", last["status"]) + (f" ({last['end_reason']})" if last.get("end_reason") else ""),
        f"{frames:,} frames from {len(last.get('frames', {}))} cameras",
        f"{events:,} events from {len(last.get('events', {}))} sensors",
        f"{last.get('bytes_written', 0) / 1e6:.1f} MB",
        f"{len(losses)} loss record(s)" if losses else "nothing lost",
    ]
    return ", ".join(parts)


def wait_for_take(
    client: DaemonClient,
    path: str,
    on_status: Any = None,
    timeout_s: float | None = None,
    status_timeout_s: float | None = None,
) -> dict[str, Any]:
    """Poll until the daemon reports `path` as its last take; returns that summary. TimeoutError
    when `timeout_s` passes first (None: wait as long as the take runs); each status request
    waits `status_timeout_s` (None: the client's own deadline)."""
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    while True:
        t = client.call("status", timeout_s=status_timeout_s)
        if on_status is not None:
            on_status(t)
        last = t.get("last_take")
        if last and last["path"] == path and t.get("take") != path:
            return dict(last)
        if deadline is not None and time.monotonic() >= deadline:
            raise TimeoutError(f"take {path} was not sealed within {timeout_s:g} s")
        time.sleep(0.2)


def _report_last(last: dict[str, Any]) -> None:
    ended = f", {last['end_reason']}" if last.get("end_reason") else ""
    typer.echo(f"take: {last['path']} ({last.get('verdict', last['status'])}{ended})")
    if last.get("error"):
        raise fail(last["error"], code=1)


def capture_via_daemon(
    client: DaemonClient, duration: float | None, label: str | None, json_out: bool, progress: Any
) -> dict[str, Any]:
    """Ask the daemon for a take and follow it to the end; the daemon's summary of it."""
    from rigd.app.service.client import DaemonRequestError, DaemonUnavailableError

    try:
        res = client.call("capture", timeout_s=CAPTURE_START_TIMEOUT_S, duration_s=duration, label=label)
    except DaemonRequestError as exc:
        raise fail(exc) from exc
    except DaemonUnavailableError as exc:
        log.error("capture request unanswered: %s", exc)
        _err.print(
            f"[bold red]error:[/] the daemon at {client.endpoint} did not answer the capture request "
            f"({exc}); a take it may have started is in its take_dir, and `rigd recover` seals it "
            "if it was left unfinished",
            soft_wrap=True,
            highlight=False,
        )
        raise typer.Exit(code=DAEMON_LOST_EXIT) from None
    path = res["take"]
    if not json_out:
        _err.print(f"capturing through the daemon at {client.endpoint}: {path}")
    try:
        try:
            last = wait_for_take(client, path, progress)
        except KeyboardInterrupt:
            client.call("stop", reason="interrupted (Ctrl-C)")
            last = wait_for_take(client, path)
    except DaemonUnavailableError as exc:
        raise _daemon_lost(client, path, exc) from None
    if json_out:
        typer.echo(json.dumps(last, indent=2))
    if last.get("error") or not json_out:
        _report_last(last)
    return last


def _daemon_lost(client: DaemonClient, path: str, exc: DaemonUnavailableError) -> typer.Exit:
    """The daemon stopped answering mid-take: say so in one line, with where the take is.

    No traceback: the daemon going away (killed, crashed, host trouble) is an operating
    condition, and what the operator needs is the take's path and how to seal it."""
    log.error("daemon lost during take %s: %s", path, exc)
    _err.print(
        f"[bold red]error:[/] the daemon at {client.endpoint} stopped answering during the take "
        f"({exc}); the take is {path}; if it was left unfinished, `rigd recover {path}` seals it",
        soft_wrap=True,
        highlight=False,
    )
    return typer.Exit(code=DAEMON_LOST_EXIT)


def find_for_command(connect: str | None, local: bool) -> DaemonClient | None:
    """The daemon to use, or None to work in-process; explicit --connect must answer."""
    if local:
        return None
    from rigd.app.service.client import find_daemon

    endpoint = control_endpoint(connect)
    try:
        client = find_daemon(endpoint, timeout_s=2.0)
    except RigdError as exc:  # another user's daemon: say so rather than capture beside it
        raise fail(exc) from exc
    if client is None and connect:
        raise fail(ConfigError(f"--connect: no rigd daemon answers at {connect}"), code=3)
    return client
