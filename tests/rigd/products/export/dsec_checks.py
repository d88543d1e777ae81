"""What a DSEC export's events must be, checked against the take it came from (the export
tests of a take captured whole and of one whose world split late share it)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import h5py
import numpy as np
from numpy.typing import NDArray

from rigd.take.reader import open_take


def _slice_dsec(path: Path, t0_us: int, t1_us: int) -> dict[str, NDArray[np.generic]]:
    """Events in [t0, t1) (the export's us) the way DSEC's EventSlicer finds them: ms_to_idx to a
    conservative index range, then the exact edges in t; its `t + t_offset` in t's own dtype
    (numpy >= 2 keeps a uint32 array uint32 when a Python int is added)."""
    with h5py.File(path, "r") as f:
        off = int(f["t_offset"][()])
        ms = f["ms_to_idx"][()]
        a, b = t0_us - off, t1_us - off
        lo, hi = int(ms[math.floor(a / 1000)]), int(ms[math.ceil(b / 1000)])
        t = f["events/t"][lo:hi].astype(np.int64)
        i, j = lo + np.searchsorted(t, a, "left"), lo + np.searchsorted(t, b, "left")
        return {
            "t": f["events/t"][i:j] + off,
            "x": f["events/x"][i:j],
            "y": f["events/y"][i:j],
            "p": f["events/p"][i:j],
        }


def check_dsec_events(root: Path, take: Path, res: tuple[int, int]) -> None:
    """events.h5 of every sensor against the take: windows identical, times from the origin."""
    stamps = [int(s) for s in (root / "images" / "cam0" / "timestamps.txt").read_text().split()]
    origin = json.loads((root / "split.json").read_text())["rig_time_origin_us"]
    with open_take(take) as tk:
        for sensor in tk.event_sensors:
            path = root / "events" / sensor / "events.h5"
            with h5py.File(path, "r") as f:
                assert f["events/p"].dtype == np.uint8
                assert f["events/t"].dtype == np.uint32
                assert set(np.unique(f["events/p"][()]).tolist()) <= {0, 1}
                off, n = int(f["t_offset"][()]), f["events/t"].shape[0]
                assert int(f["rig_time_origin_us"][()]) == origin
                t_all = f["events/t"][()].astype(np.int64)
            assert 0 <= off < 1000  # the origin is the take's start
            assert np.all(np.diff(t_all) >= 0)
            # cropped to the frames' span: first exposure start .. last exposure end
            assert off <= stamps[0]
            assert t_all[-1] + off <= stamps[-1] + 10_000
            assert n == len(tk.sensor(sensor).events(origin + off, origin + int(t_all[-1]) + off + 1))
            for a, b in ((stamps[3], stamps[4]), (stamps[5] + 17, stamps[-2] - 5)):
                got = _slice_dsec(path, a, b)
                ref = tk.sensor(sensor).events(origin + a, origin + b)
                assert len(ref) > 100
                assert got["t"].dtype == np.uint32
                np.testing.assert_array_equal(got["t"].astype(np.int64) + origin, ref.t)
                np.testing.assert_array_equal(got["x"], ref.x)
                # 1/0 in the file, +1/-1 from Take
                np.testing.assert_array_equal(got["p"].astype(np.int8) * 2 - 1, ref.p)
            with h5py.File(root / "events" / sensor / "rectify_map.h5", "r") as f:
                assert f["rectify_map"].shape == (res[1], res[0], 2)
