"""`rigd export TAKE --format mcap`: the take as ROS 2 messages (CDR) in one indexed MCAP file.

Topics (docs/export.md, "mcap"): `/<sensor>/events` (event_camera_msgs/EventPacket),
`/<sensor>/triggers` and `/rigd/<sensor>/clock_map` (rigd_msgs), `/<cam>/image_raw`
(sensor_msgs/Image, or `/<cam>/image_raw/compressed` PNG), `/<cam>/camera_info`, `/tf_static`,
`/rigd/trigger/pulses`. Every stream is read lazily and the streams are merged by log time, so
memory stays bounded by one message per topic plus the MCAP chunk being compressed.
"""

from __future__ import annotations

import heapq
import json
import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

from rigd.core.errors import TakeError
from rigd.core.extras import require
from rigd.core.layout import Root
from rigd.core.progress import ProgressCallback, ProgressUpdate, no_progress
from rigd.products.ros import msgdefs as m
from rigd.products.ros.streams import Msg, TakeStreams
from rigd.take.h5file import attr_text
from rigd.take.linked import TakeH5, open_take_h5
from rigd.take.reader import Take

log = logging.getLogger(__name__)

#: MCAP chunk size: big enough for zstd to work well, small enough to keep memory flat.
CHUNK_BYTES = 4 << 20
#: Stamps are `rig_us * 1000 + epoch_ns`; the epochs `--ros-epoch` offers.
EPOCHS = ("take", "rig")


@dataclass
class McapStats:
    """What one export wrote, per topic."""

    path: Path
    epoch_ns: int
    messages: dict[str, int] = field(default_factory=dict)
    types: dict[str, str] = field(default_factory=dict)
    bytes_by_topic: dict[str, int] = field(default_factory=dict)


def epoch_of(h5: TakeH5, which: str) -> int:
    """`take`: the take's creation second (UTC, UNIX ns) is rig time 0; `rig`: stamps are rig time."""
    if which == "rig":
        return 0
    if which != "take":
        raise TakeError(f"--ros-epoch {which!r}: one of {', '.join(EPOCHS)}")
    created = attr_text(h5.attrs.get(Root.CREATED_UTC, ""))
    if not created:
        return 0
    return int(datetime.fromisoformat(created).timestamp()) * 1_000_000_000


def write_metadata(mcap: Path, stats: McapStats, starts: dict[str, int], ends: dict[str, int]) -> None:
    """`metadata.yaml` beside the file, so its directory is a rosbag2 bag (`ros2 bag info DIR`,
    `ros2 bag play DIR`, rosbags' readers), in rosbag2's version 9 layout."""
    t0 = min(starts.values(), default=0)
    t1 = max(ends.values(), default=0)
    total = sum(stats.messages.values())
    lines = [
        "rosbag2_bagfile_information:",
        "  version: 9",
        "  storage_identifier: mcap",
        f"  duration:\n    nanoseconds: {t1 - t0}",
        f"  starting_time:\n    nanoseconds_since_epoch: {t0}",
        f"  message_count: {total}",
        "  topics_with_message_count:",
    ]
    for topic, n in stats.messages.items():
        typ = stats.types[topic]
        lines += [
            f"  - message_count: {n}",
            "    topic_metadata:",
            f"      name: {json.dumps(topic)}",
            f"      type: {json.dumps(typ)}",
            "      serialization_format: cdr",
            "      offered_qos_profiles: []",
            f"      type_description_hash: {json.dumps(m.typestore().hash_rihs01(typ))}",
        ]
    lines += [
        "  compression_format: ''",
        "  compression_mode: ''",
        f"  relative_file_paths:\n  - {json.dumps(mcap.name)}",
        "  files:",
        f"  - path: {json.dumps(mcap.name)}",
        f"    starting_time:\n      nanoseconds_since_epoch: {t0}",
        f"    duration:\n      nanoseconds: {t1 - t0}",
        f"    message_count: {total}",
        "  custom_data: {}",
        "  ros_distro: ''",
    ]
    (mcap.parent / "metadata.yaml").write_text("\n".join(lines) + "\n")


def _streams(s: TakeStreams) -> list[Iterator[Msg]]:
    out: list[Iterator[Msg]] = [s.take_info(), s.tf_static(), s.pulses()]
    for name in s.take.event_sensors:
        out += [s.events(name), s.trigger_edges(name)]
    out += [s.frames(cam) for cam in s.take.cameras]
    return out


def write_mcap(
    take: Take,
    out: Path,
    *,
    epoch: str = "take",
    slice_us: int = 0,
    compressed: bool = False,
    compression: str = "zstd",
    progress: ProgressCallback = no_progress,
) -> McapStats:
    """Write `take` as one MCAP file at `out` (`compression` chunks: zstd, lz4 or none; full index)."""
    writer_mod = require("mcap.writer", "--format mcap")
    if take.time_domain != "rig":
        raise TakeError(f"{take.path}: not on the rig timebase (time domain {take.time_domain})")
    with open_take_h5(take.path) as h5, out.open("wb") as f:
        stats = McapStats(out, epoch_of(h5, epoch))
        streams = TakeStreams(take, h5, stats.epoch_ns, slice_us, compressed)
        if streams.stamp(streams.t_start_us) < 0:
            raise TakeError(
                f"{take.path}: --ros-epoch {epoch}: the take has data at rig time {streams.t_start_us} us, "
                "before the epoch; MCAP log times cannot be negative (use --ros-epoch take)"
            )
        t_end = streams.t_start_us
        for cam in take.cameras:
            ts = take.camera(cam).timestamps_us
            t_end = max(t_end, int(ts[-1])) if ts.size else t_end
        for name in take.event_sensors:
            span = take.sensor(name).span
            t_end = max(t_end, span[1]) if span else t_end
        total_ms = max(1, (t_end - streams.t_start_us) // 1000)
        kind = {"zstd": "ZSTD", "lz4": "LZ4", "none": "NONE"}.get(compression)
        if kind is None:
            raise TakeError(f"--ros-compression {compression!r}: one of zstd, lz4, none")
        w = writer_mod.Writer(
            f, chunk_size=CHUNK_BYTES, compression=getattr(writer_mod.CompressionType, kind)
        )
        w.start(profile="ros2", library="rigd")
        schemas: dict[str, int] = {}
        channels: dict[str, int] = {}
        seqs: dict[str, int] = {}
        starts: dict[str, int] = {}
        ends: dict[str, int] = {}
        done_ms = -1
        for msg in heapq.merge(*_streams(streams), key=lambda x: x.log_ns):
            if msg.typename not in schemas:
                schemas[msg.typename] = w.register_schema(
                    name=msg.typename, encoding="ros2msg", data=m.schema_text(msg.typename).encode()
                )
            if msg.topic not in channels:
                channels[msg.topic] = w.register_channel(
                    topic=msg.topic, message_encoding="cdr", schema_id=schemas[msg.typename]
                )
            seq = seqs.get(msg.topic, 0)
            seqs[msg.topic] = seq + 1
            w.add_message(
                channels[msg.topic], log_time=msg.log_ns, data=msg.data, publish_time=msg.log_ns, sequence=seq
            )
            stats.messages[msg.topic] = seq + 1
            stats.types[msg.topic] = msg.typename
            starts.setdefault(msg.topic, msg.log_ns)
            ends[msg.topic] = max(ends.get(msg.topic, msg.log_ns), msg.log_ns)
            stats.bytes_by_topic[msg.topic] = stats.bytes_by_topic.get(msg.topic, 0) + len(msg.data)
            now_ms = (msg.log_ns - stats.epoch_ns) // 1_000_000 - streams.t_start_us // 1000
            if now_ms > done_ms:
                done_ms = now_ms
                progress(
                    ProgressUpdate("mcap", f"{done_ms}/{total_ms} ms", min(done_ms, total_ms), total_ms, "ms")
                )
        w.add_metadata(
            "rigd",
            {
                "take_id": take.take_id,
                "epoch_ns": str(stats.epoch_ns),
                "stamp_rule": "stamp_ns = rig_us * 1000 + epoch_ns",
                "event_sensors": ",".join(take.event_sensors),
                "cameras": ",".join(take.cameras),
            },
        )
        w.finish()
    write_metadata(out, stats, starts, ends)
    log.info("wrote %s: %d messages on %d topics", out, sum(stats.messages.values()), len(stats.messages))
    return stats
