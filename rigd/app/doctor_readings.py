"""Where `rigd doctor` gets its facts about this machine: one provider function per reading (usbfs
limit, free disk, write speed, clock source, groups, device nodes, udev rules, ...), gathered in
`Readings` so tests replace any of them to simulate a machine; `Readings()` reads the real one.
"""

from __future__ import annotations

import contextlib
import grp
import importlib.util
import os
import pwd
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from drivers.discovery import discover
from drivers.found_devices import Discovery


@dataclass(frozen=True, slots=True)
class NodeAccess:
    exists: bool
    readable: bool
    writable: bool


def _read_int(path: str) -> int | None:
    try:
        return int(Path(path).read_text().strip())
    except (OSError, ValueError):
        return None


def _clocksource() -> tuple[str, list[str]] | None:
    base = Path("/sys/devices/system/clocksource/clocksource0")
    try:
        current = (base / "current_clocksource").read_text().strip()
        available = (base / "available_clocksource").read_text().split()
    except OSError:
        return None
    return current, available


def _user_groups() -> set[str]:
    names = set()
    for gid in os.getgroups():
        try:
            names.add(grp.getgrgid(gid).gr_name)
        except KeyError:
            continue
    try:  # membership granted since login only shows in the group database
        user = pwd.getpwuid(os.getuid()).pw_name
        names |= {g.gr_name for g in grp.getgrall() if user in g.gr_mem}
    except KeyError:
        pass
    return names


def _node_access(path: str) -> NodeAccess:
    exists = os.path.exists(path)
    return NodeAccess(exists, exists and os.access(path, os.R_OK), exists and os.access(path, os.W_OK))


def _udev_rules() -> list[str]:
    found: list[str] = []
    for d in ("/etc/udev/rules.d", "/lib/udev/rules.d", "/usr/lib/udev/rules.d"):
        try:
            found += [os.path.join(d, f) for f in os.listdir(d) if "rigd" in f]
        except OSError:
            continue
    return found


def _free_disk(path: Path) -> int:
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    return shutil.disk_usage(p).free


def measure_write_mb_s(path: Path, size_mb: int = 64) -> float:
    """Sequential write of `size_mb` MiB with fsync, the way the take writer hits the disk."""
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    target = p / f".rigd-doctor-{os.getpid()}.tmp"
    block = os.urandom(1 << 20)  # incompressible, so a compressing filesystem cannot cheat
    t = time.perf_counter()
    try:
        with open(target, "wb", buffering=0) as f:
            for _ in range(size_mb):
                f.write(block)
            os.fsync(f.fileno())
        elapsed = time.perf_counter() - t
    finally:
        target.unlink(missing_ok=True)
    return size_mb / max(elapsed, 1e-9)


def _module_reason(name: str) -> str | None:
    """None when `name` is importable, else why not (without importing heavy modules twice)."""
    if name == "Aravis":
        try:
            import gi

            gi.require_version("Aravis", "0.8")
            from gi.repository import Aravis  # noqa: F401
        except (ImportError, ValueError) as exc:
            return str(exc)
        return None
    try:
        return None if importlib.util.find_spec(name) is not None else f"module {name} not found"
    except (ImportError, ValueError) as exc:
        return str(exc)


def _hdf5_filters() -> dict[str, bool]:
    import h5py

    with contextlib.suppress(ImportError):
        import hdf5plugin  # noqa: F401 - registers the filters with HDF5
    ids = {"lz4": 32004, "zstd": 32015, "gzip": 1}
    return {name: bool(h5py.h5z.filter_avail(fid)) for name, fid in ids.items()}


@dataclass(slots=True)
class Readings:
    """Where each check gets its facts; replace any provider to simulate a machine."""

    usbfs_memory_mb: Callable[[], int | None] = field(
        default=lambda: _read_int("/sys/module/usbcore/parameters/usbfs_memory_mb")
    )
    free_disk_bytes: Callable[[Path], int] = _free_disk
    disk_write_mb_s: Callable[[Path], float] = measure_write_mb_s
    clocksource: Callable[[], tuple[str, list[str]] | None] = _clocksource
    rmem_max: Callable[[], int | None] = field(default=lambda: _read_int("/proc/sys/net/core/rmem_max"))
    user_groups: Callable[[], set[str]] = _user_groups
    is_root: Callable[[], bool] = field(default=lambda: os.geteuid() == 0)
    node_access: Callable[[str], NodeAccess] = _node_access
    udev_rules: Callable[[], list[str]] = _udev_rules
    discovery: Callable[[], Discovery] = discover
    module_reason: Callable[[str], str | None] = _module_reason
    hdf5_filters: Callable[[], dict[str, bool]] = _hdf5_filters
