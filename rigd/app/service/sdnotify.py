"""systemd service notifications (sd_notify protocol) without a dependency.

`rigd serve` runs as a `Type=notify` unit: it says READY=1 once its control socket is bound,
pings WATCHDOG=1 from its main loop so a hung daemon is restarted, and STOPPING=1 while it
finalizes a take on SIGTERM. The protocol is one datagram of newline-separated KEY=VALUE
fields to the AF_UNIX socket named by $NOTIFY_SOCKET (a path, or `@name` for the abstract
namespace). Outside systemd every call is a cheap no-op.

A failed send is logged and counted, never raised: systemd going away (a reload, a stop
racing the daemon) must not take a running capture down with it.

Ping the watchdog from the loop whose liveness it should prove (the daemon's main loop), not
from a helper thread: a thread that pings on its own keeps a hung daemon alive.
"""

from __future__ import annotations

import logging
import os
import socket
import threading

log = logging.getLogger(__name__)

_lock = threading.Lock()
_failures = 0


def notify(*fields: str) -> bool:
    """Send `fields` (e.g. "READY=1", "STATUS=capturing take-0042") to systemd in one datagram.

    Returns True when the datagram was sent, False when not running under systemd
    ($NOTIFY_SOCKET unset) or when the send failed (logged as a warning, counted in
    `failures()`). Newlines inside a field are replaced by spaces, since the protocol splits
    fields on them and a STATUS often carries an exception text.
    """
    if not fields:
        raise ValueError("notify() needs at least one field, e.g. 'READY=1'")
    address = os.environ.get("NOTIFY_SOCKET")
    if not address:
        log.debug("not under systemd (NOTIFY_SOCKET unset); not sending %s", _summary(fields))
        return False
    payload = "\n".join(f.replace("\n", " ") for f in fields).encode("utf-8")
    try:
        target = _socket_address(address)
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.connect(target)
            sock.sendall(payload)
    except (OSError, ValueError) as exc:
        _count_failure()
        log.warning("systemd notification %s to %s failed: %s", _summary(fields), address, exc)
        return False
    log.debug("notified systemd: %s", _summary(fields))
    return True


def failures() -> int:
    """Number of notifications that could not be sent since the process started."""
    with _lock:
        return _failures


def watchdog_interval_s() -> float | None:
    """Seconds between WATCHDOG=1 pings, or None when systemd expects none.

    Half of $WATCHDOG_USEC, as sd_watchdog_enabled(3) recommends, so one late ping does not
    trip the watchdog. $WATCHDOG_PID, when set, must be this process: the variables are
    inherited by children, which must not think the watchdog is theirs.
    """
    usec = os.environ.get("WATCHDOG_USEC")
    if not usec:
        return None
    pid = os.environ.get("WATCHDOG_PID")
    if pid:
        try:
            if int(pid) != os.getpid():
                log.debug("watchdog belongs to pid %s, not to us (%d)", pid, os.getpid())
                return None
        except ValueError:
            log.warning("ignoring invalid WATCHDOG_PID=%r", pid)
            return None
    try:
        value = int(usec)
    except ValueError:
        log.warning("ignoring invalid WATCHDOG_USEC=%r", usec)
        return None
    if value <= 0:
        log.warning("ignoring invalid WATCHDOG_USEC=%r", usec)
        return None
    return value / 2 / 1e6


def _socket_address(address: str) -> str | bytes:
    """The address to connect to: a filesystem path, or an abstract name (leading NUL)."""
    if address.startswith("@"):
        return b"\0" + address[1:].encode("utf-8")
    if address.startswith("/"):
        return address
    # systemd only hands out absolute paths and @names (vsock: addresses exist in newer
    # versions for VMs; a capture host does not run rigd inside one).
    raise ValueError(f"unsupported NOTIFY_SOCKET address {address!r}")


def _count_failure() -> None:
    global _failures
    with _lock:
        _failures += 1


def _summary(fields: tuple[str, ...]) -> str:
    return ", ".join(f[:80] for f in fields)
