"""bench.reconstruction_filter: the real-data tiling, the tonic-style reference and the
dv-processing worker's protocol, on tiny inputs (no timing asserts)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.reconstruction_filter import DEFAULT_PEER, DvPeer, tile_in_time, tonic_style
from reconstruction.filters import BackgroundActivityFilter
from rigd.core.events import EventArray


def _events(n: int = 3000, w: int = 40, h: int = 30) -> EventArray:
    rng = np.random.default_rng(5)
    t = 100 + np.cumsum(rng.integers(0, 3, n))
    return EventArray.from_arrays(rng.integers(0, w, n), rng.integers(0, h, n), rng.choice([-1, 1], n), t)


def test_tile_in_time_repeats_the_recording_shifted() -> None:
    ev = _events(1000)
    tiled = tile_in_time(ev, 2500)
    assert len(tiled) == 3000
    assert np.all(np.diff(tiled.t) >= 0)
    span = int(ev.t[-1] - ev.t[0]) + 1
    for k in range(3):
        part = tiled[k * 1000 : (k + 1) * 1000]
        np.testing.assert_array_equal(part.x, ev.x)
        np.testing.assert_array_equal(part.p, ev.p)
        np.testing.assert_array_equal(part.t, ev.t + k * span)


def test_tonic_style_keeps_what_rigd_keeps() -> None:
    ev = _events()
    want = BackgroundActivityFilter(40, 30).mask(ev)
    assert 0 < want.sum() < len(ev)
    np.testing.assert_array_equal(tonic_style(ev, 40, 30), want)


@pytest.mark.skipif(not DEFAULT_PEER.exists(), reason=f"no dv-processing venv at {DEFAULT_PEER}")
def test_dv_worker_answers_in_its_own_process(tmp_path: Path) -> None:
    ev = _events()
    npz = tmp_path / "ev.npz"
    np.savez(npz, x=ev.x, y=ev.y, p=ev.p, t=ev.t)
    peer = DvPeer(DEFAULT_PEER, npz, 40, 30, None)
    try:
        assert peer.hello["events"] == len(ev)
        assert peer.hello["peer"].startswith("dv-processing")
        sec, kept_short = peer.filter(30)
        _, kept_long = peer.filter(2000)
        assert sec > 0
        assert 0 <= kept_short <= kept_long <= 1
    finally:
        peer.close()
