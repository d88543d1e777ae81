"""Crash safety of event sensors stored as EVT words: SIGKILLed writers, repair and recovery.

The rig of `test_take_recover` (exact clocks: device time = rig time + a constant), its event
sensor sending EVT 3.0 words: every flushed packet must read back from the killed take (tail
slot included) and from the recovered one, in exact rig time.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from rigd.app.testing.crash import (
    EV_PER_STEP,
    OFF_EV,
    PERIOD,
    RIG0,
    H,
    W,
    step_bytes,
)
from rigd.core.events import EventArray
from rigd.evt import StreamDecoder
from rigd.take import Take, recover_take, validate_take

#: Steps (about 1.8 kB of words each, a 256 kB chunk per ~145) each flush of the relieved writer
#: waits for: by its 4th flush the writer has stored chunks both compressed and uncompressed
#: (the mode flips every 40 steps), whatever the machine's speed.
_RELIEVED_STEPS_PER_FLUSH = 130
pytestmark = pytest.mark.slow

ROOT = Path(__file__).parents[3]


def expected_events(n: int) -> EventArray:
    dec = StreamDecoder("evt3", width=W, height=H)
    return EventArray.concatenate([dec.feed(step_bytes(k)).events for k in range(n)])


def _script(path: Path, relieve: bool = False) -> str:
    return textwrap.dedent(
        f"""
        import time
        from pathlib import Path
        from rigd.evt import StreamDecoder
        from rigd.app.testing.crash import append_words_step, journal, open_words_writer, W, H
        w = open_words_writer(Path({str(path)!r}))
        dec = StreamDecoder("evt3", width=W, height=H)
        print("START", flush=True)
        k, last, flushed = 0, time.monotonic(), 0
        per_flush = {_RELIEVED_STEPS_PER_FLUSH if relieve else 0}
        while True:
            if {relieve!r}:
                w.compress_events(k // 40 % 2 == 0)  # the writer behind every other 40 steps
            append_words_step(w, dec, k)
            k += 1
            # With `relieve`, a flush also waits for its share of steps: the chunks written in
            # each mode are then there however slow the machine is.
            if time.monotonic() - last >= 0.2 and k >= per_flush * (flushed + 1):
                w.flush(journal=journal(k))
                flushed += 1
                print(f"F {{k}}", flush=True)
                last = time.monotonic()
            time.sleep(0.0005)
        """
    )


def _run_and_kill(path: Path, flushes: int, after_s: float, relieve: bool = False) -> int:
    """Run the writer script and SIGKILL it `after_s` after its `flushes`-th flush (so the
    kill lands at a random moment of its work however slow the machine is); returns the steps
    its last completed flush covered."""
    proc = subprocess.Popen(
        [sys.executable, "-c", _script(path, relieve)], cwd=ROOT, stdout=subprocess.PIPE, text=True, bufsize=1
    )
    assert proc.stdout is not None
    assert proc.stdout.readline().strip() == "START"
    seen = []
    while len(seen) < flushes:
        line = proc.stdout.readline()
        assert line.startswith("F "), line
        seen.append(int(line.split()[1]))
    time.sleep(after_s)
    proc.send_signal(signal.SIGKILL)
    out = proc.stdout.read()
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    flushed = [
        int(x.split()[1]) for x in out.splitlines(keepends=True) if x.startswith("F ") and x.endswith("\n")
    ]
    return (flushed or seen)[-1]


def test_sigkill_at_random_moments_then_recover_words(tmp_path: Path) -> None:
    rng = np.random.default_rng(20261126)
    sealed = 0
    for i, (flushes, after_s) in enumerate(zip(rng.integers(1, 5, 5), rng.uniform(0, 0.4, 5), strict=True)):
        path = tmp_path / f"kill{i}.h5"
        n = _run_and_kill(path, int(flushes), float(after_s))
        with h5py.File(path, "r") as f:
            assert f["events/ev0"].attrs["storage"] == "evt_words"
        exp = expected_events(n + 200)
        ne = n * EV_PER_STEP
        with Take(path) as take:  # unrecovered: device time, the flushed tail included
            got = take.sensor("ev0").events()
            assert len(got) >= ne
            np.testing.assert_array_equal(got.t, exp.t[: len(got)])
        rr = recover_take(path)
        if n < 3:
            continue
        assert rr.outcome == "sealed", rr
        sealed += 1
        assert validate_take(path) == []
        with Take(path) as take:
            ev = take.sensor("ev0").events()
            assert len(ev) >= ne
            assert take.sensor("ev0").count == len(ev)
            np.testing.assert_array_equal(ev.t, exp.t[: len(ev)] - OFF_EV)
            np.testing.assert_array_equal(ev.x, exp.x[: len(ev)])
            a = RIG0 + 2 * PERIOD
            win = take.sensor("ev0").events(a, a + PERIOD)
            want = exp.t[: len(ev)] - OFF_EV
            np.testing.assert_array_equal(win.t, want[(want >= a) & (want < a + PERIOD)])
    assert sealed, "no writer got three flushes in before its kill"


def test_a_killed_take_with_chunks_stored_uncompressed_recovers_the_same(tmp_path: Path) -> None:
    """Chunks the writer stored uncompressed while behind (their filter mask says so) read and
    recover like the others, before and after the kill."""
    masks: set[int] = set()
    for i, after_s in enumerate((0.05, 0.3)):
        path = tmp_path / f"relieved{i}.h5"
        n = _run_and_kill(path, 4, after_s, relieve=True)
        exp = expected_events(n + 200)
        with Take(path) as take:
            got = take.sensor("ev0").events()
            assert len(got) >= n * EV_PER_STEP
            np.testing.assert_array_equal(got.t, exp.t[: len(got)])
        assert recover_take(path).outcome == "sealed"
        assert validate_take(path) == []
        with Take(path) as take:
            ev = take.sensor("ev0").events()
            np.testing.assert_array_equal(ev.t, exp.t[: len(ev)] - OFF_EV)
            np.testing.assert_array_equal(ev.x, exp.x[: len(ev)])
        with h5py.File(path, "r") as f:
            words = f["events/ev0/evt_words"]
            masks |= {words.id.get_chunk_info(c).filter_mask for c in range(words.id.get_num_chunks())}
    assert masks == {0, 1}
