"""The take the ROS tests export: a third of a second of the sim rig (3 Bayer RGB cameras, 2
event sensors storing EVT 3.0 words as sent, 320x180) watching the board, with its ground-truth
calibration; and bags made with rosbags' own writer."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
import pytest

from rigd.app.testing.board import capture_board_take
from rigd.products.ros import msgdefs as m

RES = (320, 180)


@pytest.fixture(scope="session")
def ros_take(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("ros-take")
    return capture_board_take(root, 0.34, RES, world="t-ros", clock="virtual", pixel_format="bayer_rg8").path


def packet(
    seq: int,
    data: bytes | np.ndarray,
    *,
    encoding: str = "evt3",
    width: int = 1280,
    height: int = 720,
    stamp_ns: int = 0,
    time_base: int = 0,
) -> bytes:
    """One event_camera_msgs/EventPacket as CDR, the way metavision_driver fills it."""
    msg = m.new(
        m.EVENT_PACKET,
        header=m.header(stamp_ns, "event_camera"),
        height=height,
        width=width,
        seq=seq,
        time_base=time_base,
        encoding=encoding,
        is_bigendian=False,
        events=np.frombuffer(bytes(data), np.uint8),
    )
    return m.serialize(msg, m.EVENT_PACKET)


def write_bag(
    path: Path, topic: str, payloads: Iterable[tuple[int, bytes]], *, storage: str = "sqlite3"
) -> Path:
    """A rosbag2 bag directory written by rosbags' Writer: (log time ns, CDR) on one topic."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conn = w.add_connection(topic, m.EVENT_PACKET, typestore=m.typestore())
        for ts, data in payloads:
            w.write(conn, ts, data)
    return path


def raw_packets(raw: Path, size: int = 4096) -> tuple[str, int, int, list[bytes]]:
    """(format, width, height, the RAW file's EVT bytes cut into `size`-byte packets)."""
    from rigd.evt import parse_raw_header

    with raw.open("rb") as f:
        hdr = parse_raw_header(f)
        body = f.read()
    return hdr.fmt, hdr.width, hdr.height, [body[i : i + size] for i in range(0, len(body), size)]
