"""Count the places that switch on a device kind: `isinstance` tests of devices, items, sinks or
settings, and comparisons with a device kind's name, in the application (the capture path,
the service, the commands) and the take package. The factory `rigd/app/capture/kinds.py` is
where kinds are mapped, and is not counted.

    python tools/kind_switches.py [--list]

`isinstance` tests of plain data (bytes, h5py nodes, exceptions, request messages) are not kind
switches and are left out (`KIND_TYPES` lists what is counted); so are `kind` fields that are
written, not tested.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOTS = ("rigd/app", "rigd/take")
FACTORY = Path("rigd/app/capture/kinds.py")
KINDS = {"rgb_camera", "event_sensor", "trigger", "frame", "events"}
#: The types a device kind is told by: the device classes, what they deliver, where it is
#: stored and how it is configured.
KIND_TYPES = {
    "Device", "RgbCamera", "EventSensor", "Trigger", "SerialTrigger", "DecodingEventSensor",
    "Frame", "EventPacket", "EventArray", "PulseBatch", "FrameItem", "EventsItem", "PulsesItem",
    "StopItem", "EventSink", "EvtWordsSink", "CameraSink", "PulseSink", "CameraSettings",
    "EventSensorSettings", "TriggerSettings", "CameraStream", "EventStream", "TriggerStream",
    "CameraConfig", "EventSensorConfig", "DeviceChannel", "TriggerChannel",
}  # fmt: skip


def _names(node: ast.expr) -> set[str]:
    out = set()
    for n in ast.walk(node):
        if isinstance(n, ast.Name):
            out.add(n.id)
        elif isinstance(n, ast.Attribute):
            out.add(n.attr)
    return out


def switches(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(), str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "isinstance":
            if len(node.args) == 2 and _names(node.args[1]) & KIND_TYPES:
                found.append((node.lineno, ast.unparse(node)))
        elif isinstance(node, ast.Compare):
            parts = [node.left, *node.comparators]
            consts = {p.value for p in parts if isinstance(p, ast.Constant) and isinstance(p.value, str)}
            named = any("kind" in _names(p) for p in parts if not isinstance(p, ast.Constant))
            if consts & KINDS and named:
                found.append((node.lineno, ast.unparse(node)))
    return found


def main() -> int:
    total = 0
    for root in ROOTS:
        for path in sorted(Path(root).rglob("*.py")):
            if path == FACTORY:
                continue
            for line, text in switches(path):
                total += 1
                if "--list" in sys.argv:
                    print(f"{path}:{line}: {text}")
    print(f"kind switches outside the factory: {total}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
