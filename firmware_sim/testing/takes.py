"""Small synthetic takes written through `TakeWriter`, with what went in kept for comparison.

`make_take`: one camera (12x16 RGB), one 64x48 event sensor with trigger events, ten pulses;
its events appended unevenly (pieces smaller than a chunk, one spanning several, a flush
between), the clocks mapped by `MAPS`.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.events import EventArray, TriggerEvents
from rigd.core.frames import Frame
from rigd.core.schema import SyncReport
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.take import TakeWriter
from rigd.take.seal import finalize_take

W, H = 64, 48
CAM_SHAPE = (12, 16, 3)
MAPS = {
    "cam0": ClockMap(device_ref_us=1_000_000, rig_ref_us=5_000_123, rate=1.00008, frac_us=0.25),
    "ev0": ClockMap(device_ref_us=400_000, rig_ref_us=5_000_000, rate=0.999905, frac_us=-0.4),
}
FIRST_PULSE = 5_010_000


@dataclass
class Written:
    path: Path
    ev_t_device: np.ndarray
    ev: EventArray
    frame_t_device: np.ndarray
    trig_t_device: np.ndarray
    pulses_t: np.ndarray


def make_events(n: int, t0: int, seed: int = 0) -> EventArray:
    rng = np.random.default_rng(seed)
    t = t0 + np.cumsum(rng.integers(0, 40, n))  # includes equal timestamps
    return EventArray.from_arrays(rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, 2, n), t)


def make_take(
    path: Path,
    *,
    finalize: bool = True,
    n_events: int = 20_000,
    compression: str = "lz4",
    n_frames: int = 9,
    fsync: bool = False,
) -> Written:
    cfg = WriterConfig(event_compression=compression, event_chunk=1024, fsync=fsync)
    w = TakeWriter(
        path, rig_config_json='{"name": "test-rig"}', take_id="take-1", config=cfg, rigd_version="t"
    )
    w.add_trigger(DeviceInfo(kind="trigger", spec="sim://t/trigger"))
    w.add_camera("cam0", DeviceInfo(kind="rgb_camera", spec="sim://t/cam0"), CAM_SHAPE, np.uint8, "{}")
    w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="sim://t/ev0"), W, H, "{}")
    ev = make_events(n_events, 400_000)
    # Uneven appends: some smaller than a chunk, one spanning several chunks.
    cuts = [0, 1, 500, 3000, 3001, 9000, n_events]
    for a, b in itertools.pairwise(cuts):
        w.append_events("ev0", ev[a:b])
        if a == 3000:
            w.flush()  # a partial chunk on disk, appended to later
    frame_t = 1_010_000 + np.arange(n_frames, dtype=np.int64) * 33_333
    for i, t in enumerate(frame_t):
        img = np.full(CAM_SHAPE, i * 10, np.uint8)
        w.append_frame("cam0", Frame(img, int(t), 8000, i, 1000 + i))
    trig_t = 400_100 + np.arange(20, dtype=np.int64) * 16_000
    w.append_triggers(
        "ev0", TriggerEvents(trig_t, np.tile([1, 0], 10).astype(np.uint8), np.zeros(20, np.uint8))
    )
    pulses_t = FIRST_PULSE + np.arange(10, dtype=np.int64) * 33_333
    w.append_pulses(PulseBatch(np.arange(10, dtype=np.int64), pulses_t, np.arange(10, dtype=np.int64)))
    if finalize:
        report = SyncReport(
            rate_hz=30.0, n_pulses=10, t_first_pulse_us=FIRST_PULSE, t_last_pulse_us=int(pulses_t[-1])
        )
        finalize_take(w, MAPS, {"cam0": np.arange(n_frames, dtype=np.int64) + 100}, report)
    w.close()
    return Written(path, ev.t.copy(), ev, frame_t, trig_t, pulses_t)
