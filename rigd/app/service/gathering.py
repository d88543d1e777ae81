"""The coordinator's end of a multi-host take: copy each host's sealed part here, then join."""

from __future__ import annotations

import functools
from pathlib import Path

from rigd.app.config import RigConfig
from rigd.app.take_gather import default_client, fetch_part
from rigd.take.parts import PartRef, join_take

#: How long one request to a host may wait while a part is copied.
GATHER_TIMEOUT_S = 30.0


def gather_part(config: RigConfig, host: str, name: str, dest: Path) -> Path:
    """Copy `host`'s part `name` into `dest` (checked by size and sha256); where it is."""
    local = dest / name
    more = functools.partial(default_client, config.hosts[host], GATHER_TIMEOUT_S)
    fetch_part(more(), local, more)
    return local


def join_parts(
    out: Path,
    coordinator: Path,
    hosts: dict[str, tuple[Path | None, tuple[str, ...]]],
    missing: dict[str, str],
) -> None:
    """Write the joined take `out` from the coordinator's part and each other host's (or why not)."""
    refs = [PartRef(h, None if p is None else Path(p.name), devices) for h, (p, devices) in hosts.items()]
    join_take(out, Path(coordinator.name), refs, missing=missing)
