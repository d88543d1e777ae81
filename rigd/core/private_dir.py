"""The one rule for a directory that holds a socket: this user's alone.

A socket in a directory others can write into can be replaced by theirs (the daemon's control
socket, the simulated trigger cable); every socket directory rigd uses is checked here."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from rigd.core.errors import ConfigError


def check_private_dir(d: Path, what: str, hint: str) -> None:
    """ConfigError (prefixed `what`) unless `d` belongs to this user and only this user may
    write into it; `hint` says how to get one."""
    st = d.stat()
    if st.st_uid != os.getuid():
        raise ConfigError(f"{what}: {d} belongs to uid {st.st_uid}, not to this user ({os.getuid()})")
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise ConfigError(
            f"{what}: {d} is writable by group or others (mode {stat.S_IMODE(st.st_mode):o}); {hint}"
        )
