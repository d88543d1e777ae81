"""Sync accuracy of captured takes against the simulator's ground truth.

    python -m bench.sync_accuracy [--duration 5] [--jitter 0,2,10] [--replug cam1]

For each trigger jitter setting, captures a take on the sim rig (+-100 ppm device clocks)
and prints per device: the fit residual RMS (what the report shows: the jitter the device
saw) and the RMS error of the take's timestamps in rig time against the exact truth, for
frame exposure starts and for events. `--replug CAM` unplugs that camera 1.5 s in for 1 s
and brings it back with its clock restarted (`clock_reset=1`): its row then measures how well
the take ties the restarted clock back onto the old one.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import uuid
from pathlib import Path

import h5py
import numpy as np

from firmware_sim.world import get_world
from rigd.app.capture import run_capture
from rigd.app.config import default_sim_rig
from rigd.core.schema import DeviceSync
from rigd.core.timebase import ClockMap
from rigd.take.reader import Take


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=5.0)
    ap.add_argument("--jitter", default="0,2,10", help="comma-separated trigger jitter sigmas, us")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=360)
    ap.add_argument("--replug", default=None, help="camera to unplug and replug with its clock restarted")
    args = ap.parse_args()
    print(
        f"{'jitter us':>9} {'device':<6} {'drift ppm':>10} {'fit rms us':>11} {'ts err rms us':>14} {'n':>9}"
    )
    for jitter in [float(j) for j in args.jitter.split(",")]:
        world = f"sync-{uuid.uuid4().hex[:8]}"
        cfg = default_sim_rig(world=world, resolution=(args.width, args.height), pixel_format="mono8")
        cfg.trigger.spec = cfg.trigger.spec.replace("jitter_us=2", f"jitter_us={jitter:g}")
        if args.replug:
            cams = {c.name: c for c in cfg.cameras}
            if args.replug not in cams:
                ap.error(f"--replug: no camera {args.replug!r} (cameras: {', '.join(cams)})")
            cams[args.replug].spec += "&unplug_at_s=1.5&unplug_for_s=1&clock_reset=1"
        out = Path(tempfile.mkdtemp(prefix="rigd-sync-"))
        try:
            res = run_capture(cfg, out, args.duration, reconnect_interval_s=0.2)
            for w in res.report.warnings:
                if "clock restarted" in w:
                    print(f"  ({w})")
            truth = get_world(world).truth
            box = truth.clocks["trigger"]
            with Take(res.path) as take, h5py.File(res.path, "r") as f:
                for cam in take.cameras:
                    counters = f[f"frames/{cam}/frame_counter"][:]
                    true_by_counter = {c: t for c, t, _ in truth.frames[cam]}
                    expected = np.array([box.at(true_by_counter[int(c)]) for c in counters])
                    err = take.camera(cam).timestamps_us - expected
                    _row(jitter, cam, res.report.devices[cam], err)
                for sensor in take.event_sensors:
                    d = res.report.devices[sensor]
                    cmap = ClockMap(d.device_ref_us, d.rig_ref_us, d.rate, d.frac_us)
                    t_rig = take.sensor(sensor).events().t
                    dev = truth.clocks[sensor]
                    true_us = (cmap.to_device(t_rig).astype(np.float64) - dev.offset_us) / dev.rate
                    _row(jitter, sensor, d, t_rig - box.at(true_us))
        finally:
            shutil.rmtree(out, ignore_errors=True)


def _row(jitter: float, name: str, dev: DeviceSync, err: np.ndarray) -> None:
    rms = float(np.sqrt(np.mean(err**2))) if err.size else float("nan")
    fit = f"{dev.drift_ppm:>10.2f} {dev.residual_rms_us:>11.3f}"
    print(f"{jitter:>9g} {name:<6} {fit} {rms:>14.3f} {err.size:>9}")


if __name__ == "__main__":
    main()
