"""The simulated trigger cable: one sim world's trigger wire and clock, carried to other processes.

A multi-host rig has one trigger line wired to every device. In simulation each host's
daemon is its own process with its own `SimWorld`; the cable joins the worlds of one name:
the *lead* world (the one with the trigger box) listens on a Unix socket, *follower* worlds
connect to it, and

- every edge fired on the lead's `TriggerWire` is fired on every follower's wire with the same
  true time and pulse index;
- on the real clock, followers adopt the lead's epoch (CLOCK_MONOTONIC is one clock on one
  machine), so true times agree; an edge that reaches a follower's event sensor after it
  encoded that slice is counted there (`triggers_late`), never dropped silently;
- on the virtual clock, the clocks form ONE discrete-event clock (`firmware_sim.clock.ClockLink`):
  the lead advances only when nothing holds time locally and every follower has taken in all
  it was sent and reports idle, to the earliest deadline over all processes; followers move
  where the lead sends them, wake their due sleepers (holding), and report idle with their
  next deadline once nothing holds time there. Edges go before the advance that follows them
  (one ordered stream, and the lead waits for their acknowledgement), so a follower's sensor
  makes exactly the events and trigger words it would make in a one-process world. Followers
  also adopt the lead's host epoch, so the host times their devices stamp (epoch + virtual
  time, `firmware_sim.clock.VirtualHostClock`) agree with the lead's.

The lead's clock does not start (box START) before `cable_followers` followers are connected
(bounded: `cable_wait_s`). A follower that hangs up is dropped with a warning and time goes on
for the others; a follower whose lead hangs up stops advancing (its devices still close), and
the next spec of that world opens a fresh world that connects again.

Spec parameters (`cable_params` builds them): `cable=<absolute socket path>`,
`cable_role=lead|follow`, on the lead `cable_followers=N` (and optionally `cable_stall_s=`: a
virtual-clock follower that owes an acknowledgement that long is dropped), optionally
`cable_wait_s=`. The
socket's directory must be private to the user (owner-only, not group or other writable).
The wire format and the two ends live in `firmware_sim.cable_link`.
"""

from __future__ import annotations

import math
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal
from urllib.parse import urlencode

from rigd.core.errors import ConfigError
from rigd.core.private_dir import check_private_dir as check_owner_only

if TYPE_CHECKING:
    from drivers.registry import DeviceSpec

CableRole = Literal["lead", "follow"]
CABLE_ROLES: tuple[CableRole, ...] = ("lead", "follow")
#: The spec parameters of the cable (every `sim://` device kind takes them).
CABLE_PARAMS = frozenset({"cable", "cable_role", "cable_followers", "cable_wait_s", "cable_stall_s"})
#: A follower waits this long (wall seconds) for the lead to listen, by default.
FOLLOW_WAIT_S = 10.0
#: The lead's START waits this long for missing followers, by default: below the host driver's
#: default reply timeout (1 s), so a missing follower is the box's ERR, not a timeout.
LEAD_WAIT_S = 0.5
#: Virtual clock: a follower that owes the lead an acknowledgement this long (wall seconds) is
#: hung (stopped, not dead) and is dropped, so it stalls the shared time no longer, by default.
STALL_S = 30.0
MAX_FOLLOWERS = 64
MAX_STALL_S = 3600.0
MAX_WAIT_S = 600.0
#: sockaddr_un.sun_path holds 108 bytes with the terminating NUL.
MAX_SOCKET_PATH = 107


@dataclass(frozen=True, slots=True)
class CableParams:
    """One world's end of the cable, as its specs give it."""

    path: str
    role: CableRole
    followers: int = 0
    """Lead: followers that must be connected before its clock starts."""
    wait_s: float | None = None
    """None: the role's default (`FOLLOW_WAIT_S`, `LEAD_WAIT_S`)."""
    stall_s: float | None = None
    """Lead: drop a follower that owes an acknowledgement this long (None: `STALL_S`; 0: never)."""

    @property
    def stall(self) -> float:
        return STALL_S if self.stall_s is None else self.stall_s

    @property
    def wait(self) -> float:
        if self.wait_s is not None:
            return self.wait_s
        return LEAD_WAIT_S if self.role == "lead" else FOLLOW_WAIT_S

    def disagreement(self, other: CableParams | None) -> str | None:
        """The first spec parameter on which `other` says something else, or None."""
        if other is None:
            return "cable"
        for name, mine, theirs in (
            ("cable", self.path, other.path),
            ("cable_role", self.role, other.role),
            ("cable_followers", self.followers, other.followers),
            ("cable_wait_s", self.wait_s, other.wait_s),
            ("cable_stall_s", self.stall_s, other.stall_s),
        ):
            if mine != theirs:
                return name
        return None


def cable_params(
    path: str | Path,
    role: CableRole,
    followers: int | None = None,
    wait_s: float | None = None,
    stall_s: float | None = None,
) -> str:
    """The spec query string of a cable end (`cable=...&cable_role=lead&cable_followers=2`), for
    configs, tests and benches to append to a `sim://` spec."""
    pairs: list[tuple[str, str]] = [("cable", str(path)), ("cable_role", role)]
    if followers is not None:
        pairs.append(("cable_followers", str(followers)))
    if wait_s is not None:
        pairs.append(("cable_wait_s", f"{wait_s:g}"))
    if stall_s is not None:
        pairs.append(("cable_stall_s", f"{stall_s:g}"))
    return urlencode(pairs, safe="/")


def parse_cable(spec: DeviceSpec) -> CableParams | None:
    """The spec's cable end, or None when it has no `cable=`; ConfigError naming the parameter."""
    given = sorted(CABLE_PARAMS & set(spec.params))
    if not given:
        return None
    where = f"device spec {spec.raw!r}"
    if "cable" not in spec.params or "cable_role" not in spec.params:
        raise ConfigError(
            f"{where}: {', '.join(given)} need both cable=<socket path> and cable_role=lead|follow"
        )
    path, role = spec.params["cable"], spec.params["cable_role"]
    if role not in CABLE_ROLES:
        raise ConfigError(f"{where}: cable_role={role!r} (use lead or follow)")
    if not os.path.isabs(path) or "\x00" in path:
        raise ConfigError(f"{where}: cable={path!r} must be an absolute path of a Unix socket")
    if len(os.fsencode(path)) > MAX_SOCKET_PATH:
        raise ConfigError(
            f"{where}: cable={path!r} is longer than a Unix socket path may be ({MAX_SOCKET_PATH} bytes)"
        )
    followers = 0
    if role == "lead":
        if "cable_followers" not in spec.params:
            raise ConfigError(f"{where}: cable_role=lead needs cable_followers=N (followers to wait for)")
        text = spec.params["cable_followers"]
        if not (text.isascii() and text.isdigit()) or int(text) > MAX_FOLLOWERS:
            raise ConfigError(f"{where}: cable_followers={text!r} out of range (allowed: 0..{MAX_FOLLOWERS})")
        followers = int(text)
    elif "cable_followers" in spec.params:
        raise ConfigError(f"{where}: cable_followers is the lead's (cable_role=lead), not a follower's")
    wait_s = _seconds(spec, "cable_wait_s", MAX_WAIT_S)
    stall_s = _seconds(spec, "cable_stall_s", MAX_STALL_S)
    if stall_s is not None and role != "lead":
        raise ConfigError(f"{where}: cable_stall_s is the lead's (cable_role=lead), not a follower's")
    return CableParams(os.path.normpath(path), role, followers, wait_s, stall_s)


def _seconds(spec: DeviceSpec, name: str, limit: float) -> float | None:
    if name not in spec.params:
        return None
    text = spec.params[name]
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (0 <= value <= limit):  # also refuses nan
        raise ConfigError(f"device spec {spec.raw!r}: {name}={text!r} out of range (allowed: 0..{limit:g} s)")
    return value


def check_private_dir(path: str, *, create: bool) -> None:
    """The cable's socket directory must be the user's alone: a socket others can replace or
    reach would let them inject trigger edges or stall the clock. The lead creates it (0700)."""
    d = Path(path).parent
    if create:
        try:
            d.mkdir(mode=0o700, parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(f"trigger cable {path}: cannot create its directory {d}: {exc}") from exc
    try:
        st = d.stat()
    except OSError as exc:
        raise ConfigError(f"trigger cable {path}: its directory {d} is not there: {exc}") from exc
    if not stat.S_ISDIR(st.st_mode):
        raise ConfigError(f"trigger cable {path}: {d} is not a directory")
    check_owner_only(d, f"trigger cable {path}", "use a private directory or chmod 700 it")


__all__ = [
    "CABLE_PARAMS",
    "CableParams",
    "CableRole",
    "cable_params",
    "check_private_dir",
    "parse_cable",
]
