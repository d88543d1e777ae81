"""Flags more than one command takes, checked the same way everywhere."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from rigd.app.commands.consoles import fail
from rigd.core.errors import ConfigError


def sim_clock_flag(value: str, config: Path | None, applies_to: str) -> Literal["real", "virtual"]:
    """`--sim-clock`: real or virtual, and virtual only for a rig rigd makes itself (a config
    says so per device, with `clock=virtual` in each sim:// spec)."""
    if value not in ("real", "virtual"):
        raise fail(ConfigError(f"--sim-clock {value!r}: use real or virtual"))
    if value == "virtual" and config is not None:
        raise fail(
            ConfigError(
                f"--sim-clock applies to {applies_to}; in a config, give every sim:// spec clock=virtual"
            )
        )
    return "virtual" if value == "virtual" else "real"
