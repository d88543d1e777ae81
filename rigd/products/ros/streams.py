"""The messages of a take's MCAP export, one lazy stream per topic (bounded memory).

Each stream yields `Msg`s in its own time order; `rigd.products.ros.mcap_export` merges them by
log time. Times: every header stamp (and log time) is `rig_us * 1000 + epoch_ns` (docs/export.md).
Event packets carry the sensor's stored EVT words as sent, one message per stored block (or per
`slice_us` of blocks that follow each other); a sensor stored as x/y/p/t columns is encoded to
EVT 3.0 per slice. `/rigd/<sensor>/clock_map` says how a decoder's times map to rig time.
"""

# ruff: noqa: N803, N806  (R, K follow the calibration literature)
from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rigd.core.errors import TakeError
from rigd.core.layout import EVENTS_GROUP, Events, TimeDomain
from rigd.core.timebase import ClockMap
from rigd.evt import Evt3Encoder, StreamDecoder, decode_from_state
from rigd.products.ros import msgdefs as m
from rigd.take.evt_read import EvtWordsEvents, is_evt_words
from rigd.take.h5file import attr_text
from rigd.take.linked import TakeH5
from rigd.take.reader import Take

#: Slice of a columns-stored sensor encoded into one EVT 3.0 packet.
COLUMN_SLICE_US = 10_000
#: ROS `sensor_msgs` encodings of rigd's stored frames, by (bayer pattern, channels, itemsize).
_BAYER = {"RGGB": "rggb", "BGGR": "bggr", "GRBG": "grbg", "GBRG": "gbrg"}


@dataclass(frozen=True, slots=True)
class Msg:
    """One message to write: its log time (ns), topic, type and CDR bytes."""

    log_ns: int
    topic: str
    typename: str
    data: bytes


def image_encoding(shape: tuple[int, ...], dtype: np.dtype[Any], bayer: str | None) -> str:
    """The `sensor_msgs/Image` encoding of a stored frame (mosaics keep their Bayer name)."""
    bits = 8 * dtype.itemsize
    if dtype.kind != "u" or bits not in (8, 16):
        raise TakeError(f"frames of dtype {dtype} have no sensor_msgs encoding")
    if len(shape) == 2:
        if bayer:
            return f"bayer_{_BAYER[bayer.upper()]}{bits}"
        return f"mono{bits}"
    if shape[2] == 3:
        return f"rgb{bits}"
    if shape[2] == 1:
        return f"mono{bits}"
    raise TakeError(f"frames of shape {shape} have no sensor_msgs encoding")


def rotation_quaternion(R: NDArray[np.float64]) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix (w >= 0)."""
    R = np.asarray(R, np.float64)
    tr = float(np.trace(R))
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        v = [0.0, 0.0, 0.0]
        v[i] = 0.25 * s
        v[j] = (R[j, i] + R[i, j]) / s
        v[k] = (R[k, i] + R[i, k]) / s
        q = v[0], v[1], v[2], (R[k, j] - R[j, k]) / s
    x, y, z, w = (float(a) for a in q)
    return (x, y, z, w) if w >= 0 else (-x, -y, -z, -w)


class TakeStreams:
    """The streams of one open take; `h5` is a second read-only handle on the same file for the
    stored EVT words (read block by block)."""

    def __init__(self, take: Take, h5: TakeH5, epoch_ns: int, slice_us: int, compressed: bool) -> None:
        self.take = take
        self.h5 = h5
        self.epoch_ns = epoch_ns
        self.slice_us = slice_us
        self.compressed = compressed
        self.calib = take.calibration or {}
        self.t_start_us = self._start_us()

    def stamp(self, rig_us: int) -> int:
        return int(rig_us) * 1000 + self.epoch_ns

    def _start_us(self) -> int:
        """The earliest time any stream starts at (the static messages' stamp)."""
        starts: list[int] = []
        pulses = self.take.pulses()
        if len(pulses):
            starts.append(int(pulses.t_us[0]))
        for cam in self.take.cameras:
            ts = self.take.camera(cam).timestamps_us
            if ts.size:
                starts.append(int(ts[0]))
        for name in self.take.event_sensors:
            span = self.take.sensor(name).span
            if span is not None:
                starts.append(span[0])
            words = self.words(name)
            if words is not None and words.first.size:
                starts.append(int(words.first[0]))
        return min(starts) if starts else 0

    # -- static ----------------------------------------------------------------------------
    def take_info(self) -> Iterator[Msg]:
        devices: dict[str, dict[str, str]] = {}
        groups = [("trigger", "trigger")]
        groups += [(f"{EVENTS_GROUP}/{n}", n) for n in self.take.event_sensors]
        groups += [(f"frames/{c}", c) for c in self.take.cameras]
        for path, name in groups:
            g = self.h5.get(path)
            if g is not None and "info_json" in g.attrs:
                devices[name] = {
                    "info": attr_text(g.attrs["info_json"]),
                    "settings": attr_text(g.attrs.get("settings_json", "{}")),
                }
        ns = self.stamp(self.t_start_us)
        msg = m.new(
            m.TAKE_INFO,
            header=m.header(ns, "rig"),
            take_id=self.take.take_id,
            epoch_ns=self.epoch_ns,
            rig_config_json=json.dumps(self.take.config),
            devices_json=json.dumps(devices),
            calibration_json=json.dumps(self._calibration_doc()),
        )
        yield Msg(ns, "/rigd/take", m.TAKE_INFO, m.serialize(msg, m.TAKE_INFO))

    def _calibration_doc(self) -> dict[str, Any]:
        """The stored calibration as `rigd.take.calibration` keeps it (result payloads, board)."""
        devices = {}
        for dev, cal in self.calib.items():
            result = cal.get("result") or {}
            devices[dev] = {k: result.get(k) for k in ("intrinsics", "pose", "source")}
        board = self.take.board_pose
        return {
            "devices": devices,
            "board": None if board is None else [board[0].tolist(), board[1].tolist()],
        }

    def tf_static(self) -> Iterator[Msg]:
        transforms = []
        for dev, cal in sorted(self.calib.items()):
            if "R" not in cal or "t" not in cal:
                continue
            R, t = np.asarray(cal["R"], np.float64), np.asarray(cal["t"], np.float64)
            centre = -R.T @ t  # x_cam = R x_rig + t: the device's origin and axes in the rig frame
            x, y, z, w = rotation_quaternion(R.T)
            transforms.append(
                m.new(
                    "geometry_msgs/msg/TransformStamped",
                    header=m.header(self.stamp(self.t_start_us), "rig"),
                    child_frame_id=dev,
                    transform=m.new(
                        "geometry_msgs/msg/Transform",
                        translation=m.new("geometry_msgs/msg/Vector3", x=centre[0], y=centre[1], z=centre[2]),
                        rotation=m.new("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w),
                    ),
                )
            )
        if transforms:
            msg = m.new(m.TF_MESSAGE, transforms=transforms)
            yield Msg(self.stamp(self.t_start_us), "/tf_static", m.TF_MESSAGE, m.serialize(msg, m.TF_MESSAGE))

    def camera_info(self, dev: str, stamp_ns: int, shape: tuple[int, ...]) -> Any | None:
        """CameraInfo of `dev` from its stored intrinsics (None: not calibrated)."""
        cal = self.calib.get(dev)
        if cal is None or "K" not in cal:
            return None
        K = np.asarray(cal["K"], np.float64).reshape(3, 3)
        dist = np.asarray(cal.get("dist", np.zeros(5)), np.float64).ravel()
        if dist.size in (12, 14) and not dist[8:].any():
            dist = dist[:8]  # OpenCV's thin-prism / tilt terms, all zero: the rational model holds it
        models = {4: "plumb_bob", 5: "plumb_bob", 8: "rational_polynomial"}
        if dist.size not in models:
            raise TakeError(
                f"calibration of {dev}: {dist.size} distortion coefficients ({dist.tolist()}) have no "
                "sensor_msgs/CameraInfo model (plumb_bob: 5, rational_polynomial: 8)"
            )
        d = np.concatenate([dist, np.zeros(1)]) if dist.size == 4 else dist
        P = np.zeros((3, 4))
        P[:, :3] = K
        h, w = shape[:2]
        return m.new(
            m.CAMERA_INFO,
            header=m.header(stamp_ns, dev),
            height=h,
            width=w,
            distortion_model=models[dist.size],
            d=d.astype(np.float64),
            k=K.ravel(),
            r=np.eye(3).ravel(),
            p=P.ravel(),
            binning_x=0,
            binning_y=0,
            roi=m.new(
                "sensor_msgs/msg/RegionOfInterest",
                x_offset=0,
                y_offset=0,
                height=0,
                width=0,
                do_rectify=False,
            ),
        )

    # -- pulses and trigger edges -------------------------------------------------------------
    def pulses(self) -> Iterator[Msg]:
        p = self.take.pulses()
        for i in range(len(p)):
            ns = self.stamp(int(p.t_us[i]))
            msg = m.new(
                m.TRIGGER_PULSE,
                header=m.header(ns, "rig"),
                index=int(p.index[i]),
                t_us=int(p.t_us[i]),
                host_time_ns=int(p.host_time_ns[i]),
            )
            yield Msg(ns, "/rigd/trigger/pulses", m.TRIGGER_PULSE, m.serialize(msg, m.TRIGGER_PULSE))

    def trigger_edges(self, name: str) -> Iterator[Msg]:
        series = self.take.sensor(name)
        tr = series.triggers
        host = series.trigger_host_times
        g = self.h5[f"{EVENTS_GROUP}/{name}/{Events.TRIGGER}"]
        dev = np.asarray(g["t_device"][...], np.int64) if "t_device" in g else np.full(len(tr), -1, np.int64)
        for i in range(len(tr)):
            ns = self.stamp(int(tr.t[i]))
            msg = m.new(
                m.TRIGGER_EDGE,
                header=m.header(ns, name),
                t_us=int(tr.t[i]),
                t_device_us=int(dev[i]) if i < dev.size else -1,
                polarity=int(tr.p[i]),
                channel=int(tr.channel[i]),
                host_time_ns=int(host[i]) if i < host.size else -1,
            )
            yield Msg(ns, f"/{name}/triggers", m.TRIGGER_EDGE, m.serialize(msg, m.TRIGGER_EDGE))

    # -- frames ----------------------------------------------------------------------------
    def frames(self, cam: str) -> Iterator[Msg]:
        fs = self.take.camera(cam, demosaic=False)
        ts = fs.timestamps_us
        shape = tuple(fs.stored_shape)
        for i in range(len(fs)):
            img = np.ascontiguousarray(fs.raw(i))
            ns = self.stamp(int(ts[i]))
            if self.compressed:
                yield self._compressed(cam, img, ns)
            else:
                enc = image_encoding(img.shape, img.dtype, fs.bayer_pattern)
                msg = m.new(
                    m.IMAGE,
                    header=m.header(ns, cam),
                    height=img.shape[0],
                    width=img.shape[1],
                    encoding=enc,
                    is_bigendian=0,
                    step=img.strides[0],
                    data=img.reshape(-1).view(np.uint8),
                )
                yield Msg(ns, f"/{cam}/image_raw", m.IMAGE, m.serialize(msg, m.IMAGE))
            info = self.camera_info(cam, ns, shape)
            if info is not None:
                yield Msg(ns, f"/{cam}/camera_info", m.CAMERA_INFO, m.serialize(info, m.CAMERA_INFO))

    def _compressed(self, cam: str, img: NDArray[Any], ns: int) -> Msg:
        """PNG (lossless: the stored pixels, a mosaic stays a mosaic)."""
        from rigd.core.extras import require

        cv2 = require("cv2", "--compressed images")
        rgb = img.ndim == 3 and img.shape[2] == 3
        ok, buf = cv2.imencode(".png", img[..., ::-1] if rgb else img)
        if not ok:
            raise TakeError(f"{cam}: PNG encoding failed")
        msg = m.new(m.COMPRESSED_IMAGE, header=m.header(ns, cam), format="png", data=buf.reshape(-1))
        return Msg(
            ns, f"/{cam}/image_raw/compressed", m.COMPRESSED_IMAGE, m.serialize(msg, m.COMPRESSED_IMAGE)
        )

    # -- events ----------------------------------------------------------------------------
    def words(self, name: str) -> EvtWordsEvents | None:
        g = self.h5[f"{EVENTS_GROUP}/{name}"]
        if not is_evt_words(g):
            return None
        cmap_text = g.attrs.get(Events.CLOCK_MAP) if self.take.time_domain == TimeDomain.RIG else None
        cmap = None if cmap_text is None else ClockMap(*json.loads(attr_text(cmap_text)))
        lo, hi = json.loads(attr_text(g.attrs.get(Events.WINDOW, "[null, null]")))
        return EvtWordsEvents(g, self.take.path, cmap, (lo, hi))

    def events(self, name: str) -> Iterator[Msg]:
        """The clock map first, then the packets."""
        words = self.words(name)
        if words is None:
            yield from self._column_events(name)
        else:
            yield from self._word_events(name, words)

    def _packet(self, name: str, seq: int, ns: int, fmt: str, data: NDArray[np.uint8]) -> Msg:
        w, h = self.take.sensor(name).geometry
        msg = m.new(
            m.EVENT_PACKET,
            header=m.header(ns, name),
            height=h,
            width=w,
            seq=seq,
            time_base=0,  # evt3: not used (event_camera_codecs; metavision_driver writes 0)
            encoding=fmt,
            is_bigendian=False,
            events=data,
        )
        return Msg(ns, f"/{name}/events", m.EVENT_PACKET, m.serialize(msg, m.EVENT_PACKET))

    def _clock_map(
        self,
        name: str,
        cmap: ClockMap,
        segments: list[tuple[int, int]],
        restarts: list[int],
        window: tuple[int, int],
    ) -> Msg:
        ns = self.stamp(self.t_start_us)
        msg = m.new(
            m.CLOCK_MAP,
            header=m.header(ns, name),
            device=name,
            device_ref_us=cmap.device_ref_us,
            rig_ref_us=cmap.rig_ref_us,
            rate=float(cmap.rate),
            frac_us=float(cmap.frac_us),
            epoch_ns=self.epoch_ns,
            offset_from_seq=np.array([s for s, _ in segments], np.uint64),
            offset_us=np.array([o for _, o in segments], np.int64),
            restart_seq=np.array(restarts, np.uint64),
            window_start_us=window[0],
            window_end_us=window[1],
            events_in_window=self.take.sensor(name).count,
        )
        return Msg(ns, f"/rigd/{name}/clock_map", m.CLOCK_MAP, m.serialize(msg, m.CLOCK_MAP))

    def _window(self, name: str) -> tuple[int, int]:
        g = self.h5[f"{EVENTS_GROUP}/{name}"]
        lo, hi = json.loads(attr_text(g.attrs.get(Events.WINDOW, "[null, null]")))
        span = self.take.sensor(name).span
        lo = lo if lo is not None else (span[0] if span else 0)
        hi = hi if hi is not None else (span[1] + 1 if span else 0)
        return int(lo), int(hi)

    def _word_events(self, name: str, words: EvtWordsEvents) -> Iterator[Msg]:
        """Every stored block (a decoder of the topic sees the stream as sent); blocks that
        follow each other merged up to `slice_us`."""
        rows = words.start.size
        groups: list[tuple[int, int]] = []
        r = 0
        while r < rows:
            e = r + 1
            while (
                e < rows
                and words.follows[e]
                and words.shift[e] == words.shift[r]
                and words.last[e] - words.first[r] < self.slice_us
            ):
                e += 1
            groups.append((r, e))
            r = e
        segments: list[tuple[int, int]] = []
        restarts: list[int] = []
        base = 0
        for seq, (a, _) in enumerate(groups):
            if seq == 0 or not words.follows[a]:
                restarts.append(seq)
                base = self._time_base(words, a)
                segments.append((seq, base + int(words.shift[a])))
            elif words.shift[a] != words.shift[groups[seq - 1][0]]:
                segments.append((seq, base + int(words.shift[a])))
        cmap = words.cmap or ClockMap.identity()
        yield self._clock_map(name, cmap, segments, restarts, self._window(name))
        for seq, (a, b) in enumerate(groups):
            data = words.stored_bytes(int(words.start[a]), int(words.start[b - 1] + words.length[b - 1]))
            yield self._packet(name, seq, self.stamp(int(words.first[a])), words.fmt, data)

    def _time_base(self, words: EvtWordsEvents, row: int) -> int:
        """What to add to the times a fresh decoder gives row's bytes to get rigd's device
        times (without the row's shift): EVT time words hold the low bits of the device clock."""
        data = words.stored_bytes(int(words.start[row]), int(words.start[row] + words.length[row]))
        ours = decode_from_state(words.fmt, data, words.states[row], words.width, words.height)
        dec = StreamDecoder(words.fmt, width=words.width, height=words.height)
        fresh = dec.feed(data).events
        held = dec.flush().events
        t_fresh = fresh.t[-1] if len(fresh) else (held.t[-1] if len(held) else None)
        if len(ours) == 0 or t_fresh is None:
            return 0
        return int(ours.t[-1]) - int(t_fresh)

    def _column_events(self, name: str) -> Iterator[Msg]:
        """A columns-stored sensor: its rig-time events encoded as EVT 3.0 per slice (times
        from `origin`, so the words start at 0 and decode without a time base)."""
        series = self.take.sensor(name)
        span = series.span
        slice_us = self.slice_us or COLUMN_SLICE_US
        origin = span[0] if span else 0
        cmap = ClockMap(0, origin, 1.0, 0.0)
        window = (origin, span[1] + 1) if span else (0, 0)
        yield self._clock_map(name, cmap, [(0, 0)], [0], window)
        if span is None:
            return
        tr = series.triggers
        enc = Evt3Encoder()
        seq = 0
        for t0 in range(span[0], span[1] + 1, slice_us):
            ev = series.events(t0, t0 + slice_us)
            a, b = np.searchsorted(tr.t, [t0, t0 + slice_us], side="left")
            part = tr[int(a) : int(b)]
            ev = ev.with_time(ev.t - origin)
            part = type(part)(part.t - origin, part.p, part.channel)
            data = np.frombuffer(enc.encode(ev, part), np.uint8)
            if data.size:
                yield self._packet(name, seq, self.stamp(t0), "evt3", data)
                seq += 1
