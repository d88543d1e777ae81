"""The Python snippets of docs/take-format.md run, unchanged, on a default take (EVT words, as the
sim rig captures it) and answer what `Take` answers: the compression filters' registration, the
`rigd.take` example, the plain-h5py window reader (on a take stored as columns too) and the DSEC
slicer on `rigd export --format dsec`'s output. The slicer here is DSEC's `EventSlicer`
algorithm rewritten (floor/ceil ms bracket, then the exact edges);
bench/consumer_checks/dsec_check.py runs DSEC's own code."""

from __future__ import annotations

import re
import shutil
import sys
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from firmware_sim.testing.takes import make_take
from rigd.app.cli import app
from rigd.app.testing.board import capture_board_take
from rigd.take import open_take

DOC = Path(__file__).parents[3] / "docs" / "take-format.md"

#: DSEC's EventSlicer (uzh-rpg/DSEC scripts/utils/eventslicer.py) in its own words, for the
#: snippet's `from eventslicer import EventSlicer`.
EVENTSLICER = """
import math
import numpy as np


class EventSlicer:
    def __init__(self, h5f):
        self.events = {k: h5f[f"events/{k}"] for k in "pxyt"}
        self.ms_to_idx = np.asarray(h5f["ms_to_idx"], dtype="int64")
        self.t_offset = int(h5f["t_offset"][()]) if "t_offset" in h5f.keys() else 0

    def get_start_time_us(self):
        return self.t_offset

    def get_events(self, t_start_us, t_end_us):
        assert t_start_us < t_end_us
        t_start_us -= self.t_offset
        t_end_us -= self.t_offset
        ms0, ms1 = math.floor(t_start_us / 1000), math.ceil(t_end_us / 1000)
        if ms0 >= self.ms_to_idx.size or ms1 >= self.ms_to_idx.size:
            return None
        i0, i1 = self.ms_to_idx[ms0], self.ms_to_idx[ms1]
        t = np.asarray(self.events["t"][i0:i1])
        a = int(np.searchsorted(t, t_start_us, side="left"))
        b = int(np.searchsorted(t, t_end_us, side="left"))
        out = {"t": t[a:b] + self.t_offset}
        for k in "pxy":
            out[k] = np.asarray(self.events[k][i0 + a : i0 + b])
        return out
"""


def python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", DOC.read_text(), re.S)


def run_block(code: str) -> dict[str, Any]:
    namespace: dict[str, Any] = {"__name__": "take_format_snippet"}
    exec(compile(code, str(DOC), "exec"), namespace)
    return namespace


def same_events(got: dict[str, np.ndarray], want: Any, t_shift: int = 0) -> None:
    assert len(got["t"]) == len(want) > 0
    np.testing.assert_array_equal(got["t"].astype(np.int64) + t_shift, want.t)
    np.testing.assert_array_equal(got["x"], want.x)
    np.testing.assert_array_equal(got["y"], want.y)
    np.testing.assert_array_equal(2 * got["p"].astype(np.int8) - 1, want.p)


@pytest.mark.slow
def test_snippets_read_a_default_take(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    cap = capture_board_take(
        tmp_path / "capture", 0.5, (160, 90), world=f"doc-{uuid.uuid4().hex[:8]}", clock="virtual"
    )
    work = tmp_path / "work"
    (work / "takes").mkdir(parents=True)
    shutil.copy(cap.path, work / "take.h5")
    shutil.copy(cap.path, work / "takes" / "take-001.h5")
    r = CliRunner().invoke(
        app, ["export", str(work / "take.h5"), "--format", "dsec", "--out", str(work / "dsec")]
    )
    assert r.exit_code == 0, r.output
    (tmp_path / "slicer").mkdir()
    (tmp_path / "slicer" / "eventslicer.py").write_text(EVENTSLICER)
    monkeypatch.syspath_prepend(str(tmp_path / "slicer"))
    monkeypatch.delitem(sys.modules, "eventslicer", raising=False)
    monkeypatch.chdir(work)

    blocks = python_blocks()
    assert len(blocks) == 4, "a new snippet in docs/take-format.md: run it here too"
    filters = run_block(blocks.pop(0))  # the plain-HDF5 user's filters: registered with h5py
    assert "hdf5plugin" in filters
    with open_take(work / "take.h5") as take:
        assert {take.sensor(s).storage for s in take.event_sensors} == {"evt_words"}  # the default
        ev0 = take.sensor("ev0")

        run_block(blocks[0])  # the rigd.take example: asserts its own count

        plain = run_block(blocks[1])
        same_events(plain["ev"], ev0.events(plain["t0"], plain["t0"] + 20_000))
        first, last = ev0.span or (0, 0)
        whole = plain["events"]("take.h5", "ev0", first, last + 1)  # every block of the take
        assert len(whole["t"]) == ev0.count

        dsec = run_block(blocks[2])
        origin, t0 = dsec["origin"], dsec["t0"]
        same_events(dsec["ev"], ev0.events(origin + t0, origin + t0 + 20_000), t_shift=origin)
    assert "Traceback" not in capsys.readouterr().err

    # The plain-h5py reader on a take stored as columns (DSEC's datasets) answers the same.
    cols = make_take(tmp_path / "columns.h5")
    with open_take(cols.path) as take:
        es = take.sensor("ev0")
        assert es.storage == "columns"
        first, last = es.span or (0, 0)
        for t0, t1 in ((first, last + 1), (first + 1_000, first + 20_000)):
            same_events(plain["events"](cols.path, "ev0", t0, t1), es.events(t0, t1))
        assert len(plain["events"](cols.path, "ev0", first - 10, first)["t"]) == 0
