"""The `rigd` command line."""

from __future__ import annotations

import logging
import sys
from importlib import metadata
from pathlib import Path
from typing import Annotated

import typer

from rigd.app.commands.calibrate import calibrate_app
from rigd.app.commands.capture import capture
from rigd.app.commands.config import default_config, version
from rigd.app.commands.consoles import fail, stderr_console, stdout_console
from rigd.app.commands.devices import devices
from rigd.app.commands.doctor import doctor
from rigd.app.commands.export import export
from rigd.app.commands.guided import guided
from rigd.app.commands.help import RigdTyper
from rigd.app.commands.inspect import convert_cmd, inspect
from rigd.app.commands.keys import keys
from rigd.app.commands.reconstruct import reconstruct
from rigd.app.commands.recover import recover_command
from rigd.app.commands.service import (
    console_url,
    serve,
    status,
    stop,
)
from rigd.app.commands.takes import takes_app
from rigd.app.commands.warmup import warmup
from rigd.core.errors import ConfigError
from rigd.core.extras import OPTIONAL, missing_extra

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


app.command("capture")(capture)
app.command("inspect")(inspect)
app.command("convert")(convert_cmd)
app.command("default-config")(default_config)
app.command("version")(version)
_add_plugin_commands()
calibrate_app.command("guided")(guided)
app.add_typer(calibrate_app, name="calibrate", help="Calibrate cameras and event sensors.")
app.command("reconstruct")(reconstruct)
app.command("export")(export)
app.command("devices")(devices)
app.command("doctor")(doctor)
app.command("serve")(serve)
app.command("recover")(recover_command)
app.add_typer(takes_app, name="takes")
app.command("status")(status)
app.command("console-url")(console_url)
app.command("stop")(stop)
app.command("keys")(keys)
app.command("warmup")(warmup)


def main() -> None:
    from rigd.app.numba_cache import ensure_numba_cache

    ensure_numba_cache()  # before numba is imported: it reads its cache settings then
    try:
        app()
    except KeyboardInterrupt:
        console.print("interrupted")
        sys.exit(130)
    except ModuleNotFoundError as exc:  # a lean install (`pip install rigd`) running the rig
        if exc.name is None or exc.name.split(".")[0] not in OPTIONAL:
            raise
        command = next((a for a in sys.argv[1:] if not a.startswith("-")), "")
        fail(missing_extra(exc.name, f"`rigd {command}`".replace(" `", "`")))  # prints the one error line
        sys.exit(2)


if __name__ == "__main__":
    main()
