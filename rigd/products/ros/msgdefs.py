"""The ROS 2 message definitions rigd writes and reads, from the `.msg` texts shipped with it.

One `rosbags` type store holds them (CDR serialization without a ROS install); `schema_text`
gives the concatenated definition an MCAP `ros2msg` schema carries (the main text, then each
dependency after a line of 80 `=` and `MSG: pkg/Name`, as `ros2 bag record` writes it).
"""

from __future__ import annotations

import functools
import re
from importlib import resources
from typing import Any

from rigd.core.extras import require

#: Every type rigd writes or reads, as ROS spells it in a bag.
EVENT_PACKET = "event_camera_msgs/msg/EventPacket"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TRIGGER_PULSE = "rigd_msgs/msg/TriggerPulse"
TRIGGER_EDGE = "rigd_msgs/msg/TriggerEdge"
CLOCK_MAP = "rigd_msgs/msg/ClockMap"
TAKE_INFO = "rigd_msgs/msg/TakeInfo"

_FIELD_TYPE = re.compile(r"^\s*([A-Za-z_][\w/]*)(\[[^\]]*\])?\s+\w+")
_PRIMITIVES = frozenset(
    {
        *("bool", "byte", "char", "string", "wstring", "float32", "float64"),
        *(f"{s}int{n}" for s in ("", "u") for n in (8, 16, 32, 64)),
    }
)


def _msg_dir() -> Any:
    return resources.files("rigd.products.ros").joinpath("msg")


@functools.cache
def msg_texts() -> dict[str, str]:
    """`pkg/msg/Name` -> the `.msg` text shipped with rigd."""
    out: dict[str, str] = {}
    for pkg in _msg_dir().iterdir():
        if not pkg.is_dir():
            continue
        for f in pkg.iterdir():
            if f.name.endswith(".msg"):
                out[f"{pkg.name}/msg/{f.name[:-4]}"] = f.read_text(encoding="utf-8")
    return out


def _dependencies(typename: str) -> list[str]:
    """The complex types `typename`'s fields use (full names), in first-use order."""
    pkg = typename.split("/")[0]
    deps: list[str] = []
    for line in msg_texts()[typename].splitlines():
        line = line.split("#", 1)[0]
        m = _FIELD_TYPE.match(line)
        if m is None or "=" in line.split()[1 if len(line.split()) > 1 else 0]:
            continue
        base = m.group(1)
        if base in _PRIMITIVES:
            continue
        full = base.replace("/", "/msg/") if "/" in base else f"{pkg}/msg/{base}"
        if full not in deps:
            deps.append(full)
    return deps


def schema_text(typename: str) -> str:
    """The `ros2msg` schema of `typename`: its text and every dependency's, depth first."""
    seen: list[str] = []

    def walk(t: str) -> None:
        for d in _dependencies(t):
            if d not in seen:
                seen.append(d)
                walk(d)

    walk(typename)
    parts = [msg_texts()[typename].rstrip("\n")]
    for d in seen:
        short = d.replace("/msg/", "/")
        parts.append(f"{'=' * 80}\nMSG: {short}\n{msg_texts()[d].rstrip(chr(10))}")
    return "\n".join(parts) + "\n"


@functools.cache
def typestore() -> Any:
    """A rosbags type store with exactly rigd's shipped definitions registered."""
    typesys = require("rosbags.typesys", "reading and writing ROS 2 messages")
    store = typesys.get_typestore(typesys.Stores.EMPTY)
    types: dict[str, Any] = {}
    for name, text in msg_texts().items():
        if name.startswith("builtin_interfaces/"):
            continue  # the empty store has them
        types.update(typesys.get_types_from_msg(text, name))
    store.register(types)
    return store


def serialize(msg: Any, typename: str) -> bytes:
    return bytes(typestore().serialize_cdr(msg, typename))


def deserialize(data: bytes | memoryview, typename: str) -> Any:
    return typestore().deserialize_cdr(data, typename)


def new(typename: str, **fields: Any) -> Any:
    """A message object of `typename` (fields by name)."""
    return typestore().types[typename](**fields)


def stamp(ns: int) -> Any:
    """builtin_interfaces/Time of `ns` nanoseconds since the epoch (negative: before it)."""
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return new("builtin_interfaces/msg/Time", sec=sec, nanosec=nsec)


def header(ns: int, frame_id: str) -> Any:
    return new("std_msgs/msg/Header", stamp=stamp(ns), frame_id=frame_id)


def stamp_ns(header_msg: Any) -> int:
    return int(header_msg.stamp.sec) * 1_000_000_000 + int(header_msg.stamp.nanosec)
