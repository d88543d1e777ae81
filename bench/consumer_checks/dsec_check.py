"""DSEC's EventSlicer (scripts/utils/eventslicer.py at the pinned commit) on rigd's dsec exports:
every reference window identical to `take.sensor(name).events`, times in uint32 without wrapping.

usage: python dsec_check.py DSEC_REPO EXPORT_DIR REFERENCE_NPZ [EXPORT_DIR REFERENCE_NPZ ...]
"""

from __future__ import annotations

import sys
from pathlib import Path

import h5py
import numpy as np


def check(slicer_cls: type, export: Path, reference: Path) -> None:
    ref = np.load(reference)
    sensors = [str(s) for s in ref["sensors"]]
    origin = int(ref["origin"])
    for s_i, sensor in enumerate(sensors):
        with h5py.File(export / "events" / sensor / "events.h5", "r") as f:
            slicer = slicer_cls(f)
            t_offset = int(f["t_offset"][()])
            windows = ref["windows"]
            n_events = 0
            for w, (a, b) in enumerate(windows):
                got = slicer.get_events(int(a), int(b))
                assert got is not None, (sensor, a, b)
                lo, hi = ref["bounds"][s_i, w]
                for key in ("x", "y", "p"):
                    np.testing.assert_array_equal(
                        got[key], ref[key][lo:hi], err_msg=f"{sensor} {key} window {w}"
                    )
                np.testing.assert_array_equal(got["t"].astype(np.int64) + origin, ref["t"][lo:hi])
                n_events += hi - lo
            print(
                f"  {export.name}/{sensor}: {len(windows)} windows identical to Take.events "
                f"({n_events} events), t {f['events/t'].dtype} + t_offset {t_offset} -> "
                f"{got['t'].dtype}, rig time origin {origin} us (> 2^32: {origin > 2**32})"
            )


def main() -> None:
    repo, rest = Path(sys.argv[1]), sys.argv[2:]
    sys.path.insert(0, str(repo / "scripts" / "utils"))
    from eventslicer import EventSlicer

    print(f"numpy {np.__version__}, h5py {h5py.__version__}")
    for export, reference in zip(rest[0::2], rest[1::2], strict=True):
        check(EventSlicer, Path(export), Path(reference))


if __name__ == "__main__":
    main()
