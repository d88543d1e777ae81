"""Compile every kernel the default rig runs before a take, and know when that is needed.

The capture path's per-event work is numba kernels cached on disk (`cache=True`). On a cold
cache (a fresh install or clone, a new `NUMBA_CACHE_DIR`, a changed source file) they take tens
of seconds to compile; a kernel compiled on a take's first packets holds the GIL while the
simulated sensors fall behind real time, and the take loses pulses. The capture preflight asks
each device to compile what it runs (`Device.warm_up`); this module is the other half: an
explicit warm-up (`rigd warmup`, and `rigd capture` on a cold cache) that runs the default sim
rig for half a second of virtual time into a scratch directory, so every kernel the capture
path touches (simulator, EVT encode/decode/scan, the take writer) compiles; a real camera's
decoder of another format is compiled by its device's own warm-up. It then writes a stamp
listing each project kernel's cache index and the source it was compiled from, so `is_warm` can
tell, with a few `stat` calls and no compiling, whether numba would load them all from its cache.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

#: Packages whose numba kernels the stamp lists.
PROJECT_ROOTS = ("rigd", "drivers", "firmware_sim", "reconstruction", "calibration")
#: Seconds of trigger pulses the warm-up take runs (virtual time: as fast as the CPU allows).
WARMUP_SECONDS = 0.5
STAMP_VERSION = 1


@dataclass(frozen=True, slots=True)
class WarmupResult:
    """What a warm-up did: the kernels it compiled (the rest loaded from the cache) and the
    kernels the stamp lists, the seconds it took and where the stamp went."""

    compiled: list[str]
    kernels: list[str]
    seconds: float
    stamp: Path | None


def stamp_path() -> Path:
    """Where the warm-up stamp lives: in `NUMBA_CACHE_DIR` when set (a new, empty one is cold),
    else in the user's cache directory, named after the numba and Python versions (an upgrade
    of either invalidates numba's cache) and the installed tree."""
    import numba

    import rigd

    # one stamp per installed tree too: two checkouts (or venvs) cache different sources
    tree = Path(rigd.__file__).resolve().parent
    key = hashlib.sha1(f"{numba.__version__} {sys.version} {tree}".encode()).hexdigest()[:12]
    given = os.environ.get("NUMBA_CACHE_DIR")
    if given:
        base = Path(given)
    else:
        home = os.environ.get("XDG_CACHE_HOME") or (
            f"{os.environ['HOME']}/.cache" if os.environ.get("HOME") else tempfile.gettempdir()
        )
        base = Path(home) / "rigd"
    return base / f"rigd-warmup-{key}.json"


def _project_dispatchers() -> Iterator[tuple[str, Any]]:
    """(module.function, dispatcher) of every numba kernel with a disk cache in the project's
    loaded modules."""
    from numba.core.dispatcher import Dispatcher

    for name, module in list(sys.modules.items()):
        if module is None or name.split(".")[0] not in PROJECT_ROOTS:
            continue
        for attr, value in list(vars(module).items()):
            if isinstance(value, Dispatcher) and value.py_func.__module__ == name:
                yield f"{name}.{attr}", value


def _cache_entry(name: str, disp: Any) -> dict[str, Any] | None:
    """The stamp's line for a kernel that ran: its cache index and its source's size and mtime
    (numba's own test of whether its cache is stale). None for a kernel without a disk cache."""
    try:
        index = Path(disp._cache._cache_file._index_path)
        source = Path(disp.py_func.__code__.co_filename)
    except AttributeError:  # NullCache (cache=False), or numba's cache internals moved
        return None
    st = source.stat()
    return {
        "kernel": name,
        "index": str(index),
        "source": str(source),
        "mtime": st.st_mtime,
        "size": st.st_size,
    }


def is_warm(path: Path | None = None) -> bool:
    """Whether the last warm-up's kernels would all load from numba's cache: its stamp exists,
    every cache index it lists still exists and every source is the one it compiled."""
    path = path or stamp_path()
    try:
        stamp = json.loads(path.read_text())
    except FileNotFoundError:
        return False
    except (OSError, ValueError) as exc:
        log.warning("unreadable warm-up stamp %s (%s): warming up again", path, exc)
        return False
    if stamp.get("version") != STAMP_VERSION or not stamp.get("kernels"):
        return False
    for entry in stamp["kernels"]:
        try:
            st = Path(entry["source"]).stat()
        except OSError:
            return False
        if (st.st_mtime, st.st_size) != (entry["mtime"], entry["size"]) or not Path(entry["index"]).exists():
            log.info("kernel %s is not in numba's cache (or its source changed)", entry["kernel"])
            return False
    return True


class _CompileListener:
    """Names each project kernel numba compiles (not loads from its cache), as it ends."""

    def __init__(self, on_kernel: Callable[[str, float], None]) -> None:
        from numba.core import event

        self.names: list[str] = []
        self._started: dict[int, float] = {}
        self._on_kernel = on_kernel
        outer = self

        class Listener(event.Listener):
            def on_start(self, ev: Any) -> None:
                outer._started[id(ev.data["dispatcher"])] = time.monotonic()

            def on_end(self, ev: Any) -> None:
                disp = ev.data["dispatcher"]
                module = disp.py_func.__module__
                if module.split(".")[0] not in PROJECT_ROOTS:
                    return
                name = f"{module}.{disp.py_func.__qualname__}"
                outer.names.append(name)
                outer._on_kernel(name, time.monotonic() - outer._started.pop(id(disp), time.monotonic()))

        self._listener = Listener()
        self._event = event

    def __enter__(self) -> _CompileListener:
        self._event.register("numba:compile", self._listener)
        return self

    def __exit__(self, *exc: object) -> None:
        self._event.unregister("numba:compile", self._listener)


def warm_up(on_kernel: Callable[[str, float], None] | None = None) -> WarmupResult:
    """Run the default sim rig for `WARMUP_SECONDS` of virtual time into a scratch directory
    (deleted after), so each kernel its capture path runs is
    compiled into numba's cache; then write the stamp `is_warm` reads. `on_kernel(name,
    seconds)` is told of each kernel compiled. A warm-up take that is not complete is logged as
    a warning with its reasons: its kernels compiled all the same, and the capture that follows
    says for itself what it kept."""
    from rigd.app.capture import run_capture
    from rigd.app.config import default_sim_rig
    from rigd.products.inspect import summarize

    t0 = time.monotonic()
    scratch = Path(tempfile.mkdtemp(prefix="rigd-warmup-"))
    try:
        with _CompileListener(on_kernel or (lambda _n, _s: None)) as listener:
            # A world of its own: the capture that follows in this process (the sim rig's world
            # is "default") starts from a world the warm-up never touched.
            world = f"rigd-warmup-{os.getpid()}-{time.monotonic_ns()}"
            result = run_capture(default_sim_rig(world=world, clock="virtual"), scratch, WARMUP_SECONDS)
            summary = summarize(result.path)
        if summary.verdict != "complete":
            log.warning(
                "the warm-up take of the default sim rig is %s: %s",
                summary.verdict,
                "; ".join(summary.verdict_reasons),
            )
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    ran = [
        _cache_entry(name, disp)
        for name, disp in sorted(_project_dispatchers(), key=lambda nd: nd[0])
        if disp.overloads
    ]
    entries = [e for e in ran if e is not None]
    target = stamp_path()
    path: Path | None = target
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_suffix(".tmp")
        tmp.write_text(json.dumps({"version": STAMP_VERSION, "kernels": entries}, indent=1))
        tmp.replace(target)
    except OSError as exc:  # the kernels are compiled and cached all the same
        log.warning("cannot write the warm-up stamp %s (%s): the next capture warms up again", target, exc)
        path = None
    seconds = time.monotonic() - t0
    log.info(
        "warm-up: %d kernels compiled, %d listed in %s, %.1f s",
        len(listener.names),
        len(entries),
        path,
        seconds,
    )
    return WarmupResult(listener.names, [e["kernel"] for e in entries], seconds, path)
