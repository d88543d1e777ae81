"""`rigd convert BAG TAKE.h5`: a rosbag2 recording (`.db3` / `.mcap`) as a take, streaming.

Each `event_camera_msgs/EventPacket` topic becomes an event sensor: its packets decoded in `seq`
order by rigd's EVT decoder (`evt3`, `evt2`, `evt21`) or unpacked (`mono`), EXT_TRIGGER words
kept as trigger edges. Each `sensor_msgs/Image` topic becomes a camera. Packets missing (a gap in
`seq`), out of order (a `seq` at or before one already decoded) or that cannot be decoded (an
unknown or changed encoding, geometry or a payload the type does not read) are counted in loss
records and named in the report's warnings; never skipped silently.

Times: a bag written by `rigd export --format mcap` carries the take's rig config and device
identities (`rigd_msgs/TakeInfo`), each sensor's clock map (`rigd_msgs/ClockMap`) and the stamp
epoch, so events, edges and frames come back in rig time, the trigger pulses with them, tied by
identity maps (a take `rigd capture --replay` plays), and only the events inside the exported take
window are written (the others counted in the take's `window_outside`). Any other bag keeps each
sensor's own clock (decoded times, microseconds) and frames their header stamps (microseconds since
the ROS epoch), and its report says that the two are not tied.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rigd import __version__
from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.errors import EventDataError, RigdError
from rigd.core.events import EventArray, TriggerEvents
from rigd.core.frames import Frame
from rigd.core.schema import DeviceSync, LossRecord, SyncReport
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.evt import FORMATS, StreamDecoder
from rigd.products.convert import removed_if_unfinished
from rigd.products.ros import bag_read
from rigd.products.ros import msgdefs as m
from rigd.take.seal import fail_take, finalize_take, set_window
from rigd.take.writer import TakeWriter

log = logging.getLogger(__name__)

Progress = Callable[[int], None]
#: Image encodings a take stores as they are, and the pixel format they are stored as.
IMAGE_FORMATS = {"mono8": "mono8", "rgb8": "rgb8", "bgr8": "rgb8", "bayer_rggb8": "bayer_rg8"}


class BagConvertError(RigdError):
    """A bag that cannot become a take (nothing to convert, unreadable)."""


def sensor_name(topic: str) -> str:
    """`/prophesee/event_camera/events` -> `prophesee_event_camera` (the device a topic is)."""
    parts = [p for p in topic.strip("/").split("/") if p]
    if len(parts) > 1 and parts[-1] in ("events", "image_raw", "image", "image_mono", "image_color"):
        parts = parts[:-1]
    return "_".join(parts) or "device"


@dataclass
class _Sensor:
    name: str
    width: int
    height: int
    encoding: str
    decoder: StreamDecoder | None = None
    last_seq: int | None = None
    missing: int = 0
    out_of_order: int = 0
    bad: int = 0
    bad_why: list[str] = field(default_factory=list)
    outside_before: int = 0
    outside_after: int = 0
    events: int = 0
    clock: Any = None
    """The rigd_msgs/ClockMap of an exported take (None: keep the sensor's clock)."""

    def note_bad(self, why: str) -> None:
        self.bad += 1
        if len(self.bad_why) < 3:
            self.bad_why.append(why)


@dataclass
class _Camera:
    name: str
    shape: tuple[int, ...]
    fmt: str
    frames: int = 0
    bad: int = 0
    bad_why: list[str] = field(default_factory=list)


class BagConverter:
    """One conversion: the writer, and per topic what it became and what was lost."""

    def __init__(
        self,
        src: Path,
        writer: TakeWriter,
        on_progress: Progress | None,
        devices: dict[str, Any] | None = None,
    ) -> None:
        self.src = src
        self.devices = devices or {}
        """{device: {"info", "settings"}} of the take a rigd export came from (rigd_msgs/TakeInfo)."""
        self.w = writer
        self.on_progress = on_progress
        self.sensors: dict[str, _Sensor] = {}
        self.cameras: dict[str, _Camera] = {}
        self.clocks: dict[str, Any] = {}
        self.epoch_ns: int | None = None
        self.pulses = 0
        self.pulse_span = (0, 0)
        self.skipped_topics: dict[str, str] = {}
        self.undecodable: dict[str, tuple[str, int, str]] = {}

    def note_undecodable(self, topic: str, typename: str, exc: Exception) -> None:
        """A payload the topic's type does not read: counted per topic."""
        _, n, first = self.undecodable.get(topic, (typename, 0, f"{type(exc).__name__}: {exc}"))
        self.undecodable[topic] = (typename, n + 1, first)

    # -- times ---------------------------------------------------------------------------
    def to_rig(self, s: _Sensor, decoded_us: np.ndarray[Any, Any], seq: int) -> np.ndarray[Any, Any]:
        c = s.clock
        if c is None:
            return decoded_us
        starts = np.asarray(c.offset_from_seq, np.int64)
        k = int(np.searchsorted(starts, seq, side="right")) - 1
        off = int(np.asarray(c.offset_us, np.int64)[k]) if k >= 0 else 0
        cmap = ClockMap(int(c.device_ref_us), int(c.rig_ref_us), float(c.rate), float(c.frac_us))
        return cmap.to_rig(decoded_us + off)

    def stamp_us(self, ns: int) -> int:
        """A header stamp as the take's time: rig us when the epoch is known."""
        if self.epoch_ns is not None:
            return (ns - self.epoch_ns) // 1000
        return ns // 1000

    # -- messages --------------------------------------------------------------------------
    def clock_map(self, msg: Any) -> None:
        self.clocks[msg.device] = msg
        self.epoch_ns = int(msg.epoch_ns)
        if msg.device in self.sensors:
            self.sensors[msg.device].clock = msg

    def pulse(self, msg: Any) -> None:
        self.w.append_pulses(
            PulseBatch(
                np.array([msg.index], np.int64),
                np.array([msg.t_us], np.int64),
                np.array([msg.host_time_ns], np.int64),
            )
        )
        self.pulses += 1
        t = int(msg.t_us)
        self.pulse_span = (t if self.pulses == 1 else self.pulse_span[0], t)

    def packet(self, topic: str, msg: Any) -> None:
        name = sensor_name(topic)
        s = self.sensors.get(name)
        if s is None:
            s = self._add_sensor(name, msg)
        seq = int(msg.seq)
        if s.last_seq is not None and seq <= s.last_seq:
            s.out_of_order += 1
            return
        if s.last_seq is not None and seq > s.last_seq + 1:
            s.missing += seq - s.last_seq - 1
        s.last_seq = seq
        if msg.encoding != s.encoding or (int(msg.width), int(msg.height)) != (s.width, s.height):
            s.note_bad(
                f"seq {seq}: {msg.encoding} {msg.width}x{msg.height}, the topic began as "
                f"{s.encoding} {s.width}x{s.height}"
            )
            return
        if s.clock is not None and seq in {int(v) for v in s.clock.restart_seq} and s.decoder is not None:
            s.decoder = StreamDecoder(s.encoding, width=s.width, height=s.height)
        try:
            ev, tr = self._decode(s, msg)
        except (EventDataError, ValueError) as exc:
            s.note_bad(f"seq {seq}: {exc}")
            return
        if len(ev):
            t = self.to_rig(s, ev.t, seq)
            keep = np.ones(len(t), bool)
            if s.clock is not None:
                before, after = t < s.clock.window_start_us, t >= s.clock.window_end_us
                keep = ~(before | after)
                s.outside_before += int(before.sum())
                s.outside_after += int(after.sum())
            ev = ev.with_time(t)[keep] if not keep.all() else ev.with_time(t)
            if len(ev):
                self.w.append_events(s.name, ev)
                s.events += len(ev)
        if len(tr):
            self.w.append_triggers(s.name, TriggerEvents(self.to_rig(s, tr.t, seq), tr.p, tr.channel))
        if self.on_progress:
            self.on_progress(sum(x.events for x in self.sensors.values()))

    def _add_sensor(self, name: str, msg: Any) -> _Sensor:
        enc = str(msg.encoding)
        s = _Sensor(name, int(msg.width), int(msg.height), enc, clock=self.clocks.get(name))
        info, settings = self._identity(name, "event_sensor", enc)
        self.w.add_event_sensor(name, info, s.width, s.height, settings)
        if enc in FORMATS:
            s.decoder = StreamDecoder(enc, width=s.width, height=s.height)
        self.sensors[name] = s
        return s

    def _identity(self, name: str, kind: str, enc: str) -> tuple[DeviceInfo, str]:
        """The device's identity and settings: the exported take's, else the bag's topic."""
        known = self.devices.get(name)
        if known is not None:
            return DeviceInfo.model_validate_json(known["info"]), str(known["settings"])
        info = DeviceInfo(
            kind=kind,
            spec=f"rosbag2://{self.src.resolve()}",
            vendor="rosbag2",
            serial=name,
            firmware=f"encoding={enc}",
        )
        return info, json.dumps({"encoding": enc})

    def _decode(self, s: _Sensor, msg: Any) -> tuple[EventArray, TriggerEvents]:
        data = np.asarray(msg.events, np.uint8)
        if s.encoding == "mono":
            if data.size % 8:
                raise ValueError(f"mono payload of {data.size} bytes is not whole 8-byte events")
            p = data.view("<u8")
            t_ns = int(msg.time_base) + (p & 0xFFFFFFFF).astype(np.int64)
            x = (p >> np.uint64(32)) & np.uint64(0xFFFF)
            y = (p >> np.uint64(48)) & np.uint64(0x7FFF)
            pol = (p >> np.uint64(63)).astype(np.int64)
            return EventArray.from_arrays(x, y, pol, t_ns // 1000), TriggerEvents.empty()
        if s.decoder is None:
            raise ValueError(
                f"encoding {s.encoding!r} is not one rigd decodes ({', '.join([*FORMATS, 'mono'])})"
            )
        d = s.decoder.feed(data)
        return d.events, d.triggers

    def image(self, topic: str, msg: Any) -> None:
        name = sensor_name(topic)
        enc = str(msg.encoding)
        cam = self.cameras.get(name)
        h, w = int(msg.height), int(msg.width)
        if cam is None:
            if enc not in IMAGE_FORMATS:
                self.skipped_topics[topic] = (
                    f"image encoding {enc!r} (a take stores {', '.join(IMAGE_FORMATS)})"
                )
                return
            shape = (h, w, 3) if IMAGE_FORMATS[enc] == "rgb8" else (h, w)
            cam = _Camera(name, shape, IMAGE_FORMATS[enc])
            info, settings = self._identity(name, "rgb_camera", enc)
            self.w.add_camera(name, info, shape, np.uint8, settings, cam.fmt)
            self.cameras[name] = cam
        data = np.asarray(msg.data, np.uint8)
        row = cam.shape[1] * (3 if len(cam.shape) == 3 else 1)
        if (
            IMAGE_FORMATS.get(enc) != cam.fmt
            or (h, w) != cam.shape[:2]
            or int(msg.step) < row
            or data.size < int(msg.step) * h
        ):
            cam.bad += 1
            if len(cam.bad_why) < 3:
                cam.bad_why.append(
                    f"frame {cam.frames + cam.bad}: {enc} {w}x{h} step {msg.step}, {data.size} bytes"
                )
            return
        img = data[: int(msg.step) * h].reshape(h, int(msg.step))[:, :row].reshape(cam.shape)
        if enc == "bgr8":
            img = img[..., ::-1]
        ns = m.stamp_ns(msg.header)
        frame = Frame(np.ascontiguousarray(img), self.stamp_us(ns), 0, cam.frames, ns, pixel_format=cam.fmt)
        self.w.append_frame(name, frame)
        cam.frames += 1

    # -- end -------------------------------------------------------------------------------
    def report(self) -> tuple[SyncReport, dict[str, dict[str, int]]]:
        warnings: list[str] = []
        losses: list[LossRecord] = []
        if self.epoch_ns is None:
            warnings.append(
                "converted rosbag2: event times are each sensor's own clock (identity map), frame "
                "times their header stamps; the two are not tied (no trigger box)"
            )
        else:
            warnings.append(
                f"converted rosbag2 written by rigd: rig times from its clock maps "
                f"(stamp epoch {self.epoch_ns} ns)"
            )
        outside: dict[str, dict[str, int]] = {}
        for s in self.sensors.values():
            for what, n, why in (
                (
                    "events",
                    s.missing,
                    f"{s.missing} EventPacket(s) missing on {s.name}'s topic (gaps in seq)",
                ),
                (
                    "events",
                    s.out_of_order,
                    f"{s.out_of_order} EventPacket(s) out of order on {s.name}'s topic "
                    "(seq at or before one already decoded), not decoded",
                ),
                (
                    "events",
                    s.bad,
                    f"{s.bad} EventPacket(s) on {s.name}'s topic could not be decoded: "
                    + "; ".join(s.bad_why),
                ),
            ):
                if n:
                    losses.append(LossRecord(device=s.name, what=what, count=n, reason=why))
                    warnings.append(why)
            if s.decoder is not None:
                skipped = {k: v for k, v in s.decoder.stats.items() if v}
                if skipped:
                    why = f"{s.encoding} decoder skipped invalid data on {s.name}'s topic: {skipped}"
                    losses.append(
                        LossRecord(device=s.name, what="events", count=sum(skipped.values()), reason=why)
                    )
                    warnings.append(why)
            if s.clock is not None:  # stored words outside the exported take window, as its take counted them
                outside[s.name] = {"stored_before": s.outside_before, "stored_after": s.outside_after}
        for c in self.cameras.values():
            if c.bad:
                why = f"{c.bad} Image(s) on {c.name}'s topic could not be stored: " + "; ".join(c.bad_why)
                losses.append(LossRecord(device=c.name, what="frames", count=c.bad, reason=why))
                warnings.append(why)
        for topic, (typename, n, first) in self.undecodable.items():
            why = f"{n} message(s) on {topic} are not {typename} CDR (first: {first})"
            what = "events" if typename == m.EVENT_PACKET else "frames"
            losses.append(LossRecord(device=sensor_name(topic), what=what, count=n, reason=why))
            warnings.append(why)
        for topic, why in self.skipped_topics.items():
            warnings.append(f"topic {topic} not converted: {why}")
        p0, p1 = self.pulse_span
        rate = (self.pulses - 1) * 1e6 / (p1 - p0) if self.pulses > 1 and p1 > p0 else 0.0
        devices = {}
        if "trigger" in self.devices:  # a rigd export: every time is rig time, tied by identity maps
            kinds = [(n, "event_sensor") for n in self.sensors] + [(n, "rgb_camera") for n in self.cameras]
            devices = {
                n: DeviceSync(
                    device=n,
                    kind=k,
                    device_ref_us=0,
                    rig_ref_us=0,
                    rate=1.0,
                    drift_ppm=0.0,
                    n_matched=0,
                    residual_rms_us=0.0,
                    residual_max_us=0.0,
                )
                for n, k in kinds
            }
        report = SyncReport(
            devices=devices,
            rate_hz=rate,
            n_pulses=self.pulses,
            t_first_pulse_us=p0 if self.pulses else None,
            t_last_pulse_us=p1 if self.pulses else None,
            warnings=warnings,
            losses=losses,
        )
        return report, outside


def bag_to_take(src: Path, dst: Path, *, on_progress: Progress | None = None) -> int:
    """Write a rosbag2 recording as a take; returns the events written."""
    if dst.exists():
        raise BagConvertError(f"{dst} exists; not overwriting a take")
    types = bag_read.topics(src)
    wanted = {m.EVENT_PACKET, m.IMAGE}
    if not any(t in wanted for t, _ in types.values()):
        found = ", ".join(f"{k} ({t})" for k, (t, _) in sorted(types.items())) or "no topics"
        raise BagConvertError(f"{src}: no event_camera_msgs/EventPacket or sensor_msgs/Image topic ({found})")
    with removed_if_unfinished(src, dst):
        n = _write(src, dst, on_progress)
    log.info("converted %s -> %s: %d events", src, dst, n)
    return n


#: What a rigd export holds beside events, images, clock maps and pulses: the take rebuilds it
#: (camera info and poses from the calibration TakeInfo carries, edges from the EVT words).
_CARRIED = (m.CAMERA_INFO, m.TF_MESSAGE, m.TRIGGER_EDGE, m.TAKE_INFO)

_HANDLERS = {
    m.EVENT_PACKET: "packet",
    m.IMAGE: "image",
}


def _store_calibration(writer: TakeWriter, conv: BagConverter, doc: dict[str, Any]) -> None:
    """The exported take's calibration, for the devices the bag gave back (a device whose topic
    carried no message has no group to hang it on: said in the report)."""
    board = doc.get("board")
    board_pose = None if board is None else (np.asarray(board[0]), np.asarray(board[1]))
    for dev, cal in (doc.get("devices") or {}).items():
        if dev not in conv.sensors and dev not in conv.cameras:
            conv.skipped_topics.setdefault(f"calibration of {dev}", "the bag holds no data of that device")
            continue
        writer.add_calibration(dev, cal["intrinsics"], cal["pose"], str(cal["source"]), board_pose)


def _write(src: Path, dst: Path, on_progress: Progress | None) -> int:
    config_json = json.dumps({"converted_from": str(src), "format": "rosbag2"})
    devices: dict[str, Any] = {}
    calibration: dict[str, Any] = {}
    first = bag_read.first_of_type(src, m.TAKE_INFO)
    if first is not None and first.encoding == "cdr":
        info = m.deserialize(first.data, m.TAKE_INFO)
        config_json, devices = info.rig_config_json, json.loads(info.devices_json)
        calibration = json.loads(info.calibration_json or "{}")
    with TakeWriter(
        dst,
        rig_config_json=config_json,
        take_id=dst.stem,
        config=WriterConfig(),
        rigd_version=__version__,
    ) as writer:
        conv = BagConverter(src, writer, on_progress, devices)
        try:
            if "trigger" in devices:
                writer.add_trigger(DeviceInfo.model_validate_json(devices["trigger"]["info"]))
            for bm in bag_read.messages(src):
                if bm.typename not in (*_HANDLERS, m.CLOCK_MAP, m.TRIGGER_PULSE):
                    if bm.typename not in _CARRIED:  # what a rigd export also holds is rebuilt, not lost
                        conv.skipped_topics.setdefault(bm.topic, f"{bm.typename} is not converted")
                    continue
                if bm.encoding != "cdr":
                    conv.skipped_topics[bm.topic] = f"serialization {bm.encoding!r}, not cdr"
                    continue
                try:
                    msg = m.deserialize(bm.data, bm.typename)
                except Exception as exc:  # noqa: BLE001  (rosbags raises plain errors on a bad payload)
                    conv.note_undecodable(bm.topic, bm.typename, exc)
                    continue
                if bm.typename == m.CLOCK_MAP:
                    conv.clock_map(msg)
                elif bm.typename == m.TRIGGER_PULSE:
                    conv.pulse(msg)
                else:
                    getattr(conv, _HANDLERS[bm.typename])(bm.topic, msg)
            if not conv.sensors and not conv.cameras:
                raise BagConvertError(f"{src}: no message of its event or image topics could be converted")
            _store_calibration(writer, conv, calibration)
            report, outside = conv.report()
            if conv.clocks:  # a rigd export: the take window it was cut to, and what fell outside
                starts = [int(c.window_start_us) for c in conv.clocks.values()]
                ends = [int(c.window_end_us) for c in conv.clocks.values()]
                set_window(writer, min(starts), max(ends), 0, outside)
            maps = {name: ClockMap.identity() for name in [*conv.sensors, *conv.cameras]}
            frame_pulse = {c: np.full(cam.frames, -1, np.int64) for c, cam in conv.cameras.items()}
            finalize_take(writer, maps, frame_pulse, report)
        except BaseException as exc:
            fail_take(writer, f"convert failed: {exc!r}")
            raise
    return sum(s.events for s in conv.sensors.values())
