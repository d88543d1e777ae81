# ruff: noqa: N806  (K follows the notation of the calibration literature)
"""DSEC layout: what DSEC's EventSlicer (and tonic.datasets.DSEC) read.

    events/<sensor>/events.h5       events/x (u16), events/y (u16), events/t (u32 us since t_offset;
                                    int64 when the span exceeds 2^32 us), events/p (u8: 1 ON, 0 OFF),
                                    ms_to_idx (u64), t_offset (i64, us since the export's time
                                    origin: under 1 ms), rig_time_origin_us (i64, rig us of time 0)
    events/<sensor>/rectify_map.h5  rectify_map (H, W, 2) f32: undistorted position of every raw
                                    pixel (only for a calibrated sensor)
    calibration/cameras.json        K_rect, resolution, T_cam_world (4x4, OpenCV) of every device
    images/<cam>/rectified/<t:06d>.png   undistorted frames
    images/<cam>/timestamps.txt          mid-exposure time of each image, us since the time origin
    images/<cam>/exposure_timestamps.txt "start_us, end_us" per image
    split.json                           train / test views, time origin (rig us)

Times are counted from the export's time origin, the take's start (the first exposure start,
rounded down to the ms), not in rig us: EventSlicer adds `t_offset` to the uint32 `t` in uint32
(numpy >= 2 keeps the array's dtype), so a rig clock past 2^32 us (71.6 min after the box's
power-on) would wrap or raise OverflowError. The rig time of any export time is
`rig_time_origin_us` + it.

Events are cropped to the frames' span (first exposure start to last exposure end). `ms_to_idx[i]`
is the first event with t >= i*1000 (relative to t_offset), for i = 0 .. ceil(span / 1000), so any
window inside the span can be sliced (EventSlicer rounds the window end up to the next ms).
"""

from __future__ import annotations

import json
import logging
import math

import numpy as np

from rigd.core.layout import Events
from rigd.core.progress import ProgressUpdate
from rigd.products.export.common import ExportPlan
from rigd.products.export.outputs import h5_output
from rigd.products.export.sensors import rectify_map, sensor_calibration

log = logging.getLogger(__name__)

#: Events per read/write step (bounded memory).
BLOCK = 1 << 22


def time_origin_us(plan: ExportPlan) -> int:
    """Rig us of the export's time 0: the first exposure start, rounded down to the ms."""
    return plan.frames.span_us[0] // 1000 * 1000


def write_events(plan: ExportPlan, sensor: str) -> int:
    """events.h5 of one sensor over the frames' span; returns the number of events."""
    take = plan.take
    t0, t1 = plan.frames.span_us
    origin = time_origin_us(plan)
    series = take.sensor(sensor)
    lo, hi = series.index(t0), series.index(t1)
    n = hi - lo
    t_dtype = np.uint32 if t1 - t0 < 2**32 else np.int64
    dest = plan.out / "events" / sensor
    dest.mkdir(parents=True, exist_ok=True)
    n_ms = math.ceil((t1 - t0) / 1000) + 1
    edges = np.arange(n_ms, dtype=np.int64) * 1000
    ms_to_idx = np.full(n_ms, n, np.uint64)
    kw = {"chunks": True, "compression": "gzip", "compression_opts": 1, "shuffle": True}
    with h5_output(dest / "events.h5") as out:
        f = out.file
        g = f.create_group("events")
        dx = g.create_dataset(Events.X, (n,), np.uint16, **kw)
        dy = g.create_dataset(Events.Y, (n,), np.uint16, **kw)
        dt = g.create_dataset(Events.T, (n,), t_dtype, **kw)
        dp = g.create_dataset(Events.P, (n,), np.uint8, **kw)
        done = 0
        last = -1  # relative time of the last event written so far
        for start in range(lo, hi, BLOCK):
            ev = series.by_index(start, min(start + BLOCK, hi))
            rel = ev.t - t0
            s = slice(done, done + len(ev))
            dx[s], dy[s], dt[s], dp[s] = ev.x, ev.y, rel.astype(t_dtype), (ev.p > 0).astype(np.uint8)
            # Edges whose first event falls in this block: last < edge <= rel[-1].
            if len(ev):
                a = int(np.searchsorted(edges, last, side="right"))
                b = int(np.searchsorted(edges, int(rel[-1]), side="right"))
                ms_to_idx[a:b] = done + np.searchsorted(rel, edges[a:b], side="left")
                last = int(rel[-1])
            done += len(ev)
            out.check()
            plan.progress(ProgressUpdate(f"events {sensor}", f"{done}/{n} events", done, n))
        f.create_dataset(Events.MS_TO_IDX, data=ms_to_idx)
        f.create_dataset(Events.T_OFFSET, data=np.int64(t0 - origin))
        f.create_dataset("rig_time_origin_us", data=np.int64(origin))
        f.attrs["polarity"] = "p: 1 ON, 0 OFF (rigd.take.reader.Take gives +1/-1)"
    calib = sensor_calibration(plan, sensor)
    if calib is not None:
        K, dist, K_rect = (np.asarray(calib[k], np.float64) for k in ("K", "dist", "K_rect"))
        size = (int(calib["image_size"][0]), int(calib["image_size"][1]))
        with h5_output(dest / "rectify_map.h5") as out:
            rmap = rectify_map(K, dist, K_rect, size)
            out.file.create_dataset("rectify_map", data=rmap, compression="gzip")
    return n


def write_calibration(plan: ExportPlan) -> None:
    """calibration/cameras.json: every device's rectified pinhole and world -> camera pose.

    DSEC ships its own cam_to_cam.yaml; this is rigd's plain-JSON equivalent, one entry per camera
    (K_rect of the exported images) and per calibrated event sensor (K_rect of rectify_map)."""
    devices: dict[str, dict[str, object]] = {}
    for c in plan.cameras:
        devices[c.name] = {
            "K_rect": c.K.tolist(),
            "resolution": list(c.size),
            "T_cam_world": c.w2c.tolist(),
            "K": c.K_src.tolist(),
            "dist": c.dist.tolist(),
        }
    for sensor in plan.take.event_sensors:
        calib = sensor_calibration(plan, sensor)
        if calib is None:
            continue
        entry: dict[str, object] = {
            "K_rect": calib["K_rect"],
            "resolution": calib["image_size"],
            "K": calib["K"],
            "dist": calib["dist"],
        }
        if "R" in calib:
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = calib["R"], calib["t"]
            entry["T_cam_world"] = T.tolist()
        devices[sensor] = entry
    dest = plan.out / "calibration" / "cameras.json"
    dest.parent.mkdir(parents=True, exist_ok=True)
    doc = {"convention": "x_cam = T_cam_world @ [x_world, 1] (OpenCV axes, metres)", "devices": devices}
    dest.write_text(json.dumps(doc, indent=1))


def write(plan: ExportPlan) -> None:
    fr, cams = plan.frames, plan.cameras
    origin = time_origin_us(plan)
    plan.write_images(lambda k, j: f"images/{cams[j].name}/rectified/{k:06d}.png")
    for j, c in enumerate(cams):
        d = plan.out / "images" / c.name
        mid = fr.t_us[:, j] - origin
        (d / "timestamps.txt").write_text("".join(f"{int(v)}\n" for v in mid))
        start = mid - fr.exposure_us[:, j] // 2
        end = start + fr.exposure_us[:, j]
        (d / "exposure_timestamps.txt").write_text(
            "# exposure_start_timestamp_us, exposure_end_timestamp_us\n"
            + "".join(f"{int(a)}, {int(b)}\n" for a, b in zip(start, end, strict=True))
        )
    write_calibration(plan)
    train = plan.train_mask
    split = {
        "kind": plan.options.split_kind,
        "train": [[int(k), cams[j].name] for k, j in np.argwhere(train)],
        "test": [[int(k), cams[j].name] for k, j in np.argwhere(~train)],
        "rig_time_origin_us": origin,
    }
    (plan.out / "split.json").write_text(json.dumps(split))
    for sensor in plan.take.event_sensors:
        n = write_events(plan, sensor)
        log.info("dsec: %s %d events", sensor, n)
