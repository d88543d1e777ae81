"""tonic on rigd's dsec export through the adapter of docs/export.md: a structured array of
tonic.datasets.DSEC.dtype holding the take's events, then a tonic transform (ToFrame) on it.

usage: python tonic_check.py EXPORT_DIR REFERENCE_NPZ
"""

from __future__ import annotations

import sys
from pathlib import Path

import h5py
import numpy as np
import tonic


def main() -> None:
    export, reference = Path(sys.argv[1]), Path(sys.argv[2])
    ref = np.load(reference)
    origin = int(ref["origin"])
    print(f"tonic {tonic.__version__}, numpy {np.__version__}")
    for sensor in (str(s) for s in ref["sensors"]):
        f = h5py.File(export / "events" / sensor / "events.h5", "r")
        ev = tonic.io.make_structured_array(
            f["events/x"][()],
            f["events/y"][()],
            f["events/t"][()].astype("int64") + f["t_offset"][()],
            f["events/p"][()],
            dtype=tonic.datasets.DSEC.dtype,
        )
        a, b = (int(v) for v in ref["windows"][0])
        sel = ev[(ev["t"] >= a) & (ev["t"] < b)]
        s_i = [str(s) for s in ref["sensors"]].index(sensor)
        lo, hi = ref["bounds"][s_i, 0]
        np.testing.assert_array_equal(sel["t"] + origin, ref["t"][lo:hi])
        np.testing.assert_array_equal(sel["x"], ref["x"][lo:hi])
        np.testing.assert_array_equal(sel["p"], ref["p"][lo:hi].astype(bool))
        w, h = int(f["events/x"][()].max()) + 1, int(f["events/y"][()].max()) + 1
        frames = tonic.transforms.ToFrame(sensor_size=(w, h, 2), n_event_bins=3)(sel)
        assert frames.sum() == len(sel), (frames.sum(), len(sel))
        print(
            f"  {sensor}: {len(ev)} events as tonic's DSEC dtype; window 0 identical ({len(sel)} events), "
            f"ToFrame {frames.shape} sums to it"
        )


if __name__ == "__main__":
    main()
