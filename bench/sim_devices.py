"""What the simulated devices of the default rig cost the host, per device, on one thread.

    python -m bench.sim_devices [--seconds 10] [--frames 100] [--slices 5000,10000,20000]

On real time the simulator shares the host's cores with the capture it feeds (on a 2-core
machine the sim devices were what fell behind), so its cost per device is what decides whether
the README's rig holds. Per event sensor of `default_sim_rig` (1280x720, sprite scene, its own
clock): CPU seconds per `--seconds` of true time for each slice length, split into the fused
render-and-compare kernel, the rest of `generate_events` (the slice's geometry), the sort and
the EVT 3.0 encoding the sensor's firmware does, with the events made (a slice length changes
only where the renders fall, within the 3 px motion bound: the count differs by a fraction of a
percent). Per camera: ms per 1280x720 frame for `Scene.render` (rgb8), the render plus
`mosaic_rggb` (how bayer_rg8 frames were made before) and `Scene.render_bayer` (how they are
made now, bit-identical to the former), best and median of `--frames` frames.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers.registry import DeviceSpec
from firmware_sim import event_kernels
from firmware_sim.placement import place
from firmware_sim.scene import lin_log
from rigd.app.config import default_sim_rig
from rigd.core.events import TriggerEvents
from rigd.core.pixels import mosaic_rggb
from rigd.evt.evt3 import Evt3Encoder

#: True time the sensors start at (the scene's sprites are all in view by then).
T0_US = 1e6


def sensor_rows(seconds: float, slices_us: list[int]) -> list[str]:
    """One row per event sensor and slice length."""
    rig = default_sim_rig(world="bench-sim-devices")
    kernel: Any = event_kernels._render_events_kernel
    spent = [0.0]

    def timed(*args: Any) -> tuple[int, int]:
        s = time.process_time()
        out: tuple[int, int] = kernel(*args)
        spent[0] += time.process_time() - s
        return out

    rows = [
        f"{'sensor':7s} {'slice ms':>8s} {'CPU s':>7s} {'kernel':>7s} {'geometry':>8s} {'sort':>6s} "
        f"{'encode':>7s} {'Mev':>7s} {'Mev/s/core':>10s}"
    ]
    for es in rig.event_sensors:
        where = place(DeviceSpec.parse(es.spec), {"threshold", "buffer_packets", "pixel_model"})
        scene, clock = where.scene, where.clock
        view = scene.view(where.name, where.width, where.height)
        event_kernels.warm_up_generator(scene, view, 0.3, clock, 0.0)
        for slice_us in slices_us:
            last = lin_log(scene.render_intensity(view, T0_US))
            ref = last.copy()
            enc, buf = Evt3Encoder(), event_kernels.EventBuffer()
            gen = srt = cod = 0.0
            n = 0
            spent[0] = 0.0
            event_kernels._render_events_kernel = timed  # type: ignore[assignment]
            try:
                for k in range(round(seconds * 1e6 / slice_us)):
                    t0, t1 = T0_US + k * slice_us, T0_US + (k + 1) * slice_us
                    a = time.process_time()
                    buf.n = 0
                    event_kernels.generate_events(scene, view, last, ref, 0.3, t0, t1, clock, buf)
                    b = time.process_time()
                    ev = buf.to_array()
                    c = time.process_time()
                    enc.encode(ev, TriggerEvents.empty())
                    enc.mark_time(clock.stamp(t1) - 1)
                    d = time.process_time()
                    gen, srt, cod, n = gen + b - a, srt + c - b, cod + d - c, n + len(ev)
            finally:
                event_kernels._render_events_kernel = kernel
            cpu = gen + srt + cod
            rows.append(
                f"{es.name:7s} {slice_us / 1000:8.0f} {cpu:7.2f} {spent[0]:7.2f} {gen - spent[0]:8.2f} "
                f"{srt:6.2f} {cod:7.2f} {n / 1e6:7.2f} {n / 1e6 / cpu:10.2f}"
            )
    return rows


def camera_rows(frames: int) -> list[str]:
    """ms per frame of each way to make a camera's frame, best and median."""
    rig = default_sim_rig(world="bench-sim-devices-cam")
    where = place(DeviceSpec.parse(rig.cameras[0].spec), set())
    scene = where.scene
    view = scene.view(where.name, where.width, where.height)
    ways: list[tuple[str, Callable[[float], object]]] = [
        ("render (rgb8)", lambda t: scene.render(view, t)),
        ("render + mosaic_rggb (bayer, before)", lambda t: mosaic_rggb(scene.render(view, t))),
        ("render_bayer (bayer, now)", lambda t: scene.render_bayer(view, t)),
    ]
    t_mid = T0_US + 4000.0
    same = np.array_equal(scene.render_bayer(view, t_mid), mosaic_rggb(scene.render(view, t_mid)))
    label = f"camera frame {where.width}x{where.height}"
    rows = [f"{label:40s} {'best ms':>8s} {'median':>8s}"]
    for name, fn in ways:
        fn(T0_US)  # compile / warm
        ts = []
        for i in range(frames):
            s = time.perf_counter()
            fn(T0_US + i * 33_333.0)
            ts.append(time.perf_counter() - s)
        rows.append(f"{name:40s} {min(ts) * 1e3:8.2f} {statistics.median(ts) * 1e3:8.2f}")
    rows.append(f"render_bayer identical to render + mosaic_rggb: {same}")
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=10.0, help="true time per sensor and slice length")
    ap.add_argument("--frames", type=int, default=100, help="frames per camera row")
    ap.add_argument("--slices", default="5000,10000,20000", help="slice lengths in us")
    args = ap.parse_args(argv)
    slices = [int(s) for s in args.slices.split(",") if s]
    for line in [*sensor_rows(args.seconds, slices), "", *camera_rows(args.frames)]:
        print(line)


if __name__ == "__main__":
    main()
