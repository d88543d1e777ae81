"""`rigd devices`: list what is attached and usable; write a config skeleton or udev rules.

Register with `app.command("devices")(devices)`. Exit code 0 even when nothing is found
(that is an answer, not an error); 2 when an output file cannot be written.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from rigd.app.commands.consoles import fail, stderr_console, stdout_console

if TYPE_CHECKING:  # the driver layer (numpy) loads when the command runs
    from drivers.found_devices import Discovery

log = logging.getLogger(__name__)
_err = stderr_console()


def _print_table(found: Discovery, out: Console) -> None:
    from drivers.found_devices import usb_speed_label

    table = Table("source", "role", "name", "spec", "usb id", "serial", "link")
    for d in found.devices:
        table.add_row(
            d.source,
            d.role,
            d.name,
            d.spec or "-",
            d.usb_id or "-",
            d.serial or "-",
            usb_speed_label(d.usb_speed_mbps) or "-",
        )
    if found.devices:
        out.print(table)
    else:
        out.print("No cameras, event sensors or trigger boxes found: nothing usable is attached.")
    for s in found.sources:
        if not s.available:
            out.print(f"[yellow]{s.source}: unavailable[/] ({s.reason})")
        else:
            out.print(f"{s.source}: {len(s.devices)} found")


def devices(
    json_out: Annotated[bool, typer.Option("--json", help="Print what was found as JSON.")] = False,
    config: Annotated[
        Path | None, typer.Option("--config", help="Write a rig config skeleton (.toml or .json) here.")
    ] = None,
    udev: Annotated[
        Path | None, typer.Option("--udev", help="Write udev rules with stable /dev/rigd-* symlinks here.")
    ] = None,
    connect: Annotated[str | None, typer.Option("--connect", help="Ask the daemon at this endpoint.")] = None,
    local: Annotated[bool, typer.Option("--local", help="Look here even if a daemon runs.")] = False,
) -> None:
    """List serial ports, USB and HID devices, V4L2 nodes and GenICam cameras rigd can use.

    With a daemon running, the daemon looks (it is the process with the device permissions)."""
    from drivers.device_setup import udev_rules, write_config_skeleton
    from drivers.discovery import discover
    from drivers.found_devices import Discovery
    from rigd.app.commands.service import find_for_command

    client = find_for_command(connect, local)
    if client is None:
        found = discover()
    else:
        with client:
            found = Discovery.from_dict(client.call("devices"))
        _err.print(f"devices as seen by the daemon at {client.endpoint}")
    out = stdout_console()
    if json_out:
        typer.echo(found.to_json())
    else:
        _print_table(found, out)
    try:
        if config is not None:
            notes = write_config_skeleton(found, config)
            _err.print(f"wrote rig config skeleton {escape(str(config))}")
            for note in notes:  # notes name TOML tables ([[cameras]]): not markup
                _err.print(f"[yellow]edit:[/] {escape(note)}", soft_wrap=True)
        if udev is not None:
            udev.parent.mkdir(parents=True, exist_ok=True)
            udev.write_text(udev_rules(found.devices), encoding="utf-8")
            _err.print(
                f"wrote udev rules {udev}; install: sudo cp {udev} /etc/udev/rules.d/99-rigd.rules "
                "&& sudo udevadm control --reload && sudo udevadm trigger"
            )
    except (OSError, ValueError) as exc:
        raise fail(exc) from exc
