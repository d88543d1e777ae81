"""The ROS consumers' side of bench.ros_acceptance, run with a scratch venv's python (mcap,
mcap-ros2-support, rosbags, evt3 from the registry; nothing of rigd is imported here).

    python ros_check.py export MCAP REF.npz WORK   # read an export, compare with the take
    python ros_check.py rawbag RAW BAG_DIR REF.npz # a .db3 bag from a RAW file; evt3's events
    python ros_check.py ecc BAG DECODER MSG OUT.npz  # event_camera_codecs' events of a bag

`export`: the mcap reader with mcap-ros2-support's decoder reads every message; each sensor's
EventPacket bytes are decoded by the evt3 package's stateful decoder (an EVT 3.0 decoder that is
not rigd's), their times mapped as the sensor's rigd_msgs/ClockMap message states (docs/export.md);
counts, every 50 ms window and every image are compared with the take's, written to REF.npz by
the project side. Then rosbags' AnyReader opens the file and `rosbags-convert` writes a sqlite3
bag (WORK/db3) for the project side to convert back. `rawbag`: rosbags' Writer records the RAW
file's EVT words as metavision_driver does (4 KiB packets, encoding evt3, time_base 0), and evt3
decodes the file for the reference. `ecc`: rosbags reads every event_camera_msgs/EventPacket of
a bag (typed by the .msg text MSG of the event_camera_msgs repository) and DECODER (a small
program over event_camera_codecs' own DecoderFactory, bench/consumer_checks/event_camera_codecs/)
decodes them in bag order, one decoder per topic as a ROS node keeps it; the events and trigger
edges go to OUT.npz per topic. One PASS/FAIL line per check; exit code 1 if any failed.
"""

from __future__ import annotations

import subprocess
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import evt3
import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

WINDOW_US = 50_000
FAILED: list[str] = []


def check(name: str, ok: bool, detail: str) -> None:
    print(f"{'PASS' if ok else 'FAIL'} {name}: {detail}", flush=True)
    if not ok:
        FAILED.append(name)


def to_rig(decoded_us: np.ndarray, clock: Any, seq: int) -> np.ndarray:
    """The ClockMap message's rule, written out from its text."""
    starts = np.asarray(clock.offset_from_seq, np.int64)
    k = int(np.searchsorted(starts, seq, side="right")) - 1
    device = decoded_us.astype(np.int64) + (int(clock.offset_us[k]) if k >= 0 else 0)
    d = (device - int(clock.device_ref_us)).astype(np.float64)
    return np.rint(d * float(clock.rate) + float(clock.frac_us)).astype(np.int64) + int(clock.rig_ref_us)


def read_export(path: Path) -> tuple[dict[str, Any], dict[str, list[Any]], dict[str, list[Any]], int]:
    clocks: dict[str, Any] = {}
    packets: dict[str, list[Any]] = defaultdict(list)
    images: dict[str, list[Any]] = defaultdict(list)
    n = 0
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, _msg, dec in reader.iter_decoded_messages(log_time_order=True):
            n += 1
            if schema.name == "rigd_msgs/msg/ClockMap":
                clocks[dec.device] = dec
            elif schema.name == "event_camera_msgs/msg/EventPacket":
                packets[channel.topic.strip("/").split("/")[0]].append(dec)
            elif schema.name == "sensor_msgs/msg/Image":
                images[channel.topic.strip("/").split("/")[0]].append(dec)
    return clocks, packets, images, n


def decode_sensor(packets: list[Any], clock: Any) -> dict[str, np.ndarray]:
    restarts = {int(s) for s in clock.restart_seq}
    dec = None
    parts: dict[str, list[np.ndarray]] = defaultdict(list)
    for pk in sorted(packets, key=lambda p: p.seq):
        if pk.encoding != "evt3":
            raise SystemExit(f"packet encoding {pk.encoding}: this check decodes evt3")
        if dec is None or pk.seq in restarts:
            dec = evt3.Decoder(sensor_width=pk.width, sensor_height=pk.height)
        ev = dec.feed(bytes(pk.events))
        t = to_rig(np.asarray(ev.timestamp), clock, pk.seq)
        keep = (t >= clock.window_start_us) & (t < clock.window_end_us)
        parts["t"].append(t[keep])
        parts["x"].append(np.asarray(ev.x)[keep])
        parts["y"].append(np.asarray(ev.y)[keep])
        parts["p"].append(np.asarray(ev.polarity)[keep])
    return {k: np.concatenate(v) for k, v in parts.items()}


def check_export(mcap: Path, ref_path: Path, work: Path) -> None:
    ref = np.load(ref_path)
    clocks, packets, images, n = read_export(mcap)
    check(
        "mcap+mcap_ros2 read",
        n == int(ref["messages"]),
        f"{n} messages decoded, the export wrote {int(ref['messages'])}",
    )
    for name in [str(s) for s in ref["sensors"]]:
        ev = decode_sensor(packets[name], clocks[name])
        want = {k: ref[f"{name}/{k}"] for k in "xypt"}
        count = int(want["t"].size)
        check(
            f"{name} count",
            ev["t"].size == count == int(clocks[name].events_in_window),
            f"evt3 decoded {ev['t'].size} in the window, take.sensor count {count}",
        )
        bad = 0
        windows = 0
        for t0 in range(int(want["t"][0]), int(want["t"][-1]) + 1, WINDOW_US):
            a0, a1 = np.searchsorted(ev["t"], [t0, t0 + WINDOW_US])
            b0, b1 = np.searchsorted(want["t"], [t0, t0 + WINDOW_US])
            got = [ev[k][a0:a1].astype(np.int64) for k in "xyt"] + [ev["p"][a0:a1] > 0]
            exp = [want[k][b0:b1].astype(np.int64) for k in "xyt"] + [want["p"][b0:b1] > 0]
            windows += 1
            bad += not all(g.shape == e.shape and np.array_equal(g, e) for g, e in zip(got, exp, strict=True))
        check(
            f"{name} 50 ms windows",
            bad == 0,
            f"{windows - bad}/{windows} windows equal take.sensor(name).events",
        )
    for cam in [str(c) for c in ref["cameras"]]:
        frames = ref[f"{cam}/frames"]
        got = images[cam]
        same = len(got) == len(frames) and all(
            np.array_equal(
                np.frombuffer(bytes(im.data), np.uint8)
                .reshape(im.height, im.step)[:, : frames.shape[2]]
                .reshape(frames.shape[1:]),
                frames[i],
            )
            for i, im in enumerate(got)
        )
        check(
            f"{cam} images",
            same,
            f"{len(got)} images vs {len(frames)} frames, encoding {got[0].encoding if got else '-'}",
        )
    from rosbags.highlevel import AnyReader

    with AnyReader([mcap]) as reader:
        counts: dict[str, int] = defaultdict(int)
        for conn, _ts, raw in reader.messages():
            reader.deserialize(raw, conn.msgtype)
            counts[conn.msgtype] += 1
    check(
        "rosbags AnyReader",
        sum(counts.values()) == n,
        f"{sum(counts.values())} messages deserialized: {dict(counts)}",
    )
    with AnyReader([mcap.parent]) as reader:  # the export directory as a rosbag2 bag (metadata.yaml)
        n_dir = sum(1 for _ in reader.messages())
    check("rosbags AnyReader on the directory", n_dir == n, f"{n_dir} messages through its metadata.yaml")
    dst = work / "db3"
    conv = Path(sys.executable).with_name("rosbags-convert")
    r = subprocess.run(
        [str(conv), "--src", str(mcap), "--dst", str(dst), "--dst-storage", "sqlite3"],
        capture_output=True,
        text=True,
        check=False,
    )
    db3 = sorted(dst.glob("*.db3")) if dst.is_dir() else []
    check(
        "rosbags-convert to sqlite3",
        r.returncode == 0 and bool(db3),
        f"{db3[0].name if db3 else r.stderr[-300:]}",
    )


def check_rawbag(raw: Path, bag: Path, ref_out: Path) -> None:
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    text = (
        Path(__file__).resolve().parents[2] / "rigd/products/ros/msg/event_camera_msgs/EventPacket.msg"
    ).read_text()
    store.register(get_types_from_msg(text, "event_camera_msgs/msg/EventPacket"))
    packet_t = store.types["event_camera_msgs/msg/EventPacket"]
    header_t, time_t = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    data = raw.read_bytes()
    end = 0
    while data[end : end + 1] == b"%":  # the OpenEB header: lines that start with '%'
        end = data.index(b"\n", end) + 1
    fields = dict(
        ln[2:].split(" ", 1) for ln in data[:end].decode(errors="replace").splitlines() if " " in ln[2:]
    )
    geometry = fields.get("geometry", "1280x720").split("x")  # gen4.1 sensors: 1280x720
    width, height = int(geometry[0]), int(geometry[1])
    body = data[end:]
    with Writer(bag, version=9) as w:
        conn = w.add_connection("/event_camera/events", "event_camera_msgs/msg/EventPacket", typestore=store)
        for seq, i in enumerate(range(0, len(body), 4096)):
            stamp = 1_700_000_000_000_000_000 + seq * 1_000_000
            msg = packet_t(
                header=header_t(
                    stamp=time_t(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id="event_camera"
                ),
                height=height,
                width=width,
                seq=seq,
                time_base=0,
                encoding="evt3",
                is_bigendian=False,
                events=np.frombuffer(body[i : i + 4096], np.uint8),
            )
            w.write(conn, stamp, store.serialize_cdr(msg, "event_camera_msgs/msg/EventPacket"))
    ev = evt3.decode_file(str(raw))
    np.savez(
        ref_out, x=np.asarray(ev.x), y=np.asarray(ev.y), p=np.asarray(ev.polarity), t=np.asarray(ev.timestamp)
    )
    print(
        f"INFO {raw.name}: {len(body)} bytes in {-(-len(body) // 4096)} packets, "
        f"evt3 decodes {len(ev)} events",
        flush=True,
    )


def decode_with_codecs(bag: Path, decoder: Path, msg: Path, out: Path) -> None:
    import struct

    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(msg.read_text(), "event_camera_msgs/msg/EventPacket"))
    topics: dict[str, int] = {}
    frames = bytearray()
    with AnyReader([bag], default_typestore=store) as reader:
        conns = [c for c in reader.connections if c.msgtype == "event_camera_msgs/msg/EventPacket"]
        for conn, _ts, raw in reader.messages(connections=conns):
            m = reader.deserialize(raw, conn.msgtype)
            tid = topics.setdefault(conn.topic, len(topics))
            enc = m.encoding.encode()
            data = bytes(m.events)
            frames += struct.pack("<BB", tid, len(enc)) + enc
            frames += struct.pack("<IIQI", m.width, m.height, m.time_base, len(data)) + data
    run = subprocess.run([str(decoder)], input=bytes(frames), capture_output=True, check=False)
    if run.returncode:
        raise SystemExit(f"{decoder} failed ({run.returncode}): {run.stderr.decode()}")
    rows = np.frombuffer(
        run.stdout,
        dtype=np.dtype(
            [("topic", "u1"), ("kind", "u1"), ("t", "<u8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")]
        ),
    )
    arrays: dict[str, np.ndarray] = {}
    for topic, tid in topics.items():
        mine = rows[rows["topic"] == tid]
        for kind, name in ((0, "ev"), (1, "trig")):
            part = mine[mine["kind"] == kind]
            for field in ("t", "x", "y", "p"):
                arrays[f"{topic}|{name}|{field}"] = np.asarray(part[field])
    np.savez(out, **arrays)
    print(
        f"INFO event_camera_codecs decoded {bag.name}: {len(topics)} topic(s), {rows.size} rows", flush=True
    )


def main() -> int:
    if sys.argv[1] == "ecc":
        decode_with_codecs(Path(sys.argv[2]), Path(sys.argv[3]), Path(sys.argv[4]), Path(sys.argv[5]))
        return 0
    if sys.argv[1] == "export":
        check_export(Path(sys.argv[2]), Path(sys.argv[3]), Path(sys.argv[4]))
    else:
        check_rawbag(Path(sys.argv[2]), Path(sys.argv[3]), Path(sys.argv[4]))
    return 1 if FAILED else 0


if __name__ == "__main__":
    sys.exit(main())
