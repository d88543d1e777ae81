"""Walk three parameters through the code and count how often the walk comes back to a module
it already left (a "return"): the rig config from `run_capture` to the devices, an event packet
from the driver to the HDF5 file, and a take to a trainer export.

    python tools/walks.py [--list] [--out DIR]

A walk is traced, not read: the functions of rigd, drivers, calibration and reconstruction that
run, in the order of their first call (a loop's second pass adds nothing), grouped into stays
(consecutive calls in one module). A return is a stay in a module visited before. The three
walks run on the default sim rig, 1 s on the virtual clock (deterministic call order):

- config: the rig config and its parts (device entries, settings), from `run_capture` on the calling
  thread: opening, checking and configuring the devices, creating the take, starting;
- packet: event packets and the queue items that carry them, on `ev0`'s acquisition thread then the writer
  thread, from the driver to the sinks;
- export: the take and its series (`Take`, `EventSeries`, `FrameSeries`), through
  `rigd export --format nerfstudio` of that take.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path
from types import FrameType
from typing import Any

from pydantic import BaseModel

PACKAGES = ("rigd", "drivers", "calibration", "reconstruction")
#: Leaf layers a walk passes through without it being a detour: the ground types and the codec.
LEAVES = ("rigd.core", "rigd.evt")
ROOT = Path(__file__).resolve().parents[1]


class Tracer:
    """First calls of project functions, per thread, while `on`, that are handed the walked
    parameter: an argument other than `self` that is one of the `objects` (by identity), or
    of one of the `walked` types."""

    def __init__(self, walked: tuple[type, ...] = (), objects: set[int] | None = None) -> None:
        self.calls: dict[str, list[tuple[str, str]]] = {}
        self.on = False
        self.walked = walked
        self.objects = objects or set()
        self._seen: dict[str, set[tuple[str, str]]] = {}
        self.back: dict[str, list[tuple[str, str]]] = {}
        """The same walk with the way back: a recorded call's return to its caller's module."""
        self._open: set[int] = set()

    def _handed(self, frame: FrameType) -> bool:
        code = frame.f_code
        names = code.co_varnames[: code.co_argcount + code.co_kwonlyargcount]
        for name in names:
            if name in ("self", "cls"):
                continue
            value = frame.f_locals.get(name)
            if id(value) in self.objects or isinstance(value, self.walked):
                return True
        return False

    def _module(self, frame: FrameType) -> str | None:
        name = frame.f_globals.get("__name__", "")
        if name.split(".")[0] not in PACKAGES or name.startswith(LEAVES):
            return None
        return str(name)

    def _caller(self, frame: FrameType) -> str | None:
        f = frame.f_back
        while f is not None:
            if (module := self._module(f)) is not None:
                return module
            f = f.f_back
        return None

    def __call__(self, frame: FrameType, event: str, arg: Any) -> Callable[..., Any] | None:
        if not self.on:
            return None
        if event == "return" and id(frame) in self._open:
            self._open.discard(id(frame))
            caller = self._caller(frame)
            if caller is not None:
                self.back.setdefault(threading.current_thread().name, []).append((caller, "<back>"))
            return None
        if event != "call":
            return None
        module = self._module(frame)
        if module is None:
            return None
        if not self._handed(frame):
            return None
        thread = threading.current_thread().name
        key = (module, frame.f_code.co_qualname)
        seen = self._seen.setdefault(thread, set())
        if key not in seen:
            seen.add(key)
            self.calls.setdefault(thread, []).append(key)
            self.back.setdefault(thread, []).append(key)
            self._open.add(id(frame))
        return None


def stays(calls: list[tuple[str, str]]) -> list[str]:
    out: list[str] = []
    for module, _ in calls:
        if not out or out[-1] != module:
            out.append(module)
    return out


def count(modules: list[str]) -> tuple[int, int, int]:
    """(stays, distinct modules, returns)."""
    seen: set[str] = set()
    returns = 0
    for m in modules:
        if m in seen:
            returns += 1
        seen.add(m)
    return len(modules), len(seen), returns


def _parts(model: BaseModel) -> set[int]:
    """Ids of a pydantic model and of every model inside it (fields, lists, dicts)."""
    found: set[int] = set()
    todo: list[Any] = [model]
    while todo:
        value = todo.pop()
        if isinstance(value, BaseModel):
            if id(value) in found:
                continue
            found.add(id(value))
            todo.extend(getattr(value, name) for name in type(value).model_fields)
        elif isinstance(value, list | tuple):
            todo.extend(value)
        elif isinstance(value, dict):
            todo.extend(value.values())
    return found


Walk = tuple[list[str], list[str]]
"""A walk's stays: going in only, and with the way back."""


def _config_and_packet_walks(out: Path) -> tuple[Walk, Walk, Path]:
    from rigd.app.capture import run_capture
    from rigd.app.capture.items import EventsItem
    from rigd.app.config import default_sim_rig
    from rigd.core.events import EventPacket

    cfg = default_sim_rig(world="walks", clock="virtual", resolution=(320, 180))
    # The config walk: the rig config and every part of it (its device entries, their settings),
    # by identity: a device's own default settings are not the rig's config.
    config_tracer = Tracer(objects=_parts(cfg))
    packet_tracer = Tracer((EventPacket, EventsItem))

    def both(frame: FrameType, event: str, arg: Any) -> None:
        thread = threading.current_thread().name
        if thread == "MainThread":
            config_tracer(frame, event, arg)
        elif thread in ("acq-ev0", "writer"):
            packet_tracer(frame, event, arg)

    threading.setprofile(both)
    sys.setprofile(both)
    config_tracer.on = packet_tracer.on = True
    try:
        result = run_capture(cfg, out, 1.0)
    finally:
        config_tracer.on = packet_tracer.on = False
        sys.setprofile(None)
        threading.setprofile(None)
    config_walk = (
        stays(config_tracer.calls.get("MainThread", [])),
        stays(config_tracer.back.get("MainThread", [])),
    )
    threads = ("acq-ev0", "writer")
    packet_walk = (
        stays([c for t in threads for c in packet_tracer.calls.get(t, [])]),
        stays([c for t in threads for c in packet_tracer.back.get(t, [])]),
    )
    return config_walk, packet_walk, result.path


def _export_walk(take: Path, out: Path) -> Walk:
    from rigd.products.export import run_export
    from rigd.products.export.common import ExportOptions
    from rigd.take.event_series import EventSeries
    from rigd.take.frame_series import FrameSeries
    from rigd.take.reader import Take

    tracer = Tracer((Take, EventSeries, FrameSeries))
    sys.setprofile(tracer)
    tracer.on = True
    try:
        run_export(ExportOptions(take=take, format="nerfstudio", out=out / "ns"))
    finally:
        tracer.on = False
        sys.setprofile(None)
    return stays(tracer.calls.get("MainThread", [])), stays(tracer.back.get("MainThread", []))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--list", action="store_true", help="print each walk's stays")
    ap.add_argument("--out", type=Path, help="where the take and export go (default: a temp dir)")
    args = ap.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="rigd-walks-"))
    config_walk, packet_walk, take = _config_and_packet_walks(out)
    export_walk = _export_walk(take, out)
    print("| walk | stays | modules | returns | with the way back: stays | returns |")
    print("|---|---:|---:|---:|---:|---:|")
    walks = (
        ("config to devices", config_walk),
        ("packet to HDF5", packet_walk),
        ("take to export", export_walk),
    )
    for name, (walk, back) in walks:
        s, m, r = count(walk)
        sb, _, rb = count(back)
        print(f"| {name} | {s} | {m} | {r} | {sb} | {rb} |")
        if args.list:
            print("  " + " > ".join(w.removeprefix("rigd.") for w in back))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
