"""`rigd default-config` and `rigd version`: what this installation is and starts from."""

from __future__ import annotations

from rigd import __version__
from rigd.app.commands.consoles import stdout_console
from rigd.app.config import default_sim_rig

out = stdout_console()


def default_config() -> None:
    """Print the built-in simulated rig config, a starting point for a real one."""
    out.print_json(default_sim_rig().model_dump_json())


def version() -> None:
    """Print the rigd version."""
    out.print(__version__)
