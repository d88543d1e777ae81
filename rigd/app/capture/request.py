"""What a take is asked for, checked before any device opens: its length, the directory it goes
to, and the file name it gets there. The command line, the control socket and the session share
these, so a bound is stated once."""

from __future__ import annotations

import os
import uuid
from datetime import UTC, datetime
from pathlib import Path

from rigd.core.errors import ConfigError

#: The longest take a capture is asked for (the control socket's bound too): 7 days.
MAX_DURATION_S = 7 * 86400.0


def check_duration(duration_s: float, what: str = "duration") -> None:
    """A take's length: more than 0 s and at most `MAX_DURATION_S` (NaN and inf refused)."""
    if not 0 < duration_s <= MAX_DURATION_S:
        raise ConfigError(
            f"{what} {duration_s:g} s: a take lasts more than 0 s and at most {MAX_DURATION_S:g} s (7 days)"
        )


def check_out_dir(out_dir: Path, what: str = "take directory") -> None:
    """The take directory is one, or can be made, and is writable, before a device is opened."""
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"{what} {out_dir}: not a directory")
    base = next((d for d in (out_dir, *out_dir.parents) if d.exists()), Path("."))
    if not base.is_dir():
        raise ConfigError(f"{what} {out_dir}: {base} is not a directory")
    if not os.access(base, os.W_OK | os.X_OK):
        raise ConfigError(f"{what} {out_dir}: {base} is not writable")


def new_take_path(out_dir: Path, rig_name: str, label: str | None = None) -> Path:
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    middle = f"-{label}" if label else ""
    return out_dir / f"{rig_name}{middle}-{stamp}-{uuid.uuid4().hex[:6]}.h5"
