"""Which host names count as this machine only: the one rule that decides where the daemon's
HTTP endpoints (console, metrics) may listen without an explicit secret."""

from __future__ import annotations

import ipaddress


def is_loopback(host: str) -> bool:
    """True for loopback addresses (`127.0.0.0/8`, `::1`, bracketed or not) and `localhost`."""
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
