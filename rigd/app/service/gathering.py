"""Copying a host's part here and joining the parts (placeholder until the join lands)."""

from __future__ import annotations

from pathlib import Path

from rigd.app.config import RigConfig
from rigd.app.service.host_links import HostLink
from rigd.app.service.multihost import Join
from rigd.core.errors import TakeError


def gather_part(link: HostLink, name: str, dest: Path) -> Path:
    raise TakeError(f"gathering {name} from {link.name} is not built yet")


def join_parts(config: RigConfig) -> Join:
    def join(
        out: Path,
        coordinator: Path,
        hosts: dict[str, tuple[Path | None, tuple[str, ...]]],
        missing: dict[str, str],
    ) -> None:
        raise TakeError(f"joining {out} is not built yet")

    return join
