"""Torch representations of packed windows against the numpy ones, window by window.

Runs on the CPU here; `RIGD_TEST_TORCH_DEVICE=cuda` runs the same tests on a GPU
(`bench/gpu_check.sh`), where a missing CUDA device is a failure, not a skip.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from reconstruction.packed_events import PackedEvents, concat_packed, pack_events
from reconstruction.representations import event_frame, time_surface, voxel_grid_bincount
from rigd.core.events import EventArray
from tests.reconstruction.parity import ATOL, RTOL, assert_voxel_parity

torch = pytest.importorskip("torch")
tr = pytest.importorskip("reconstruction.torch_representations")

W, H = 7, 5
BIG = 10_000_000_000  # ~2.8 h of microseconds
DEVICE = os.environ.get("RIGD_TEST_TORCH_DEVICE", "cpu")
if DEVICE.startswith("cuda") and not torch.cuda.is_available():
    raise RuntimeError(f"RIGD_TEST_TORCH_DEVICE={DEVICE} but torch sees no CUDA device")


def ev_of(x: list[int], y: list[int], p: list[int], t: list[int]) -> EventArray:
    return EventArray.from_arrays(x, y, p, t)


def on_device(windows: list[PackedEvents]) -> object:
    return tr.EventBatch.from_packed(concat_packed(windows)).to(DEVICE)


def check_window(
    got_vox: object,
    got_vox_n: object,
    got_frame: object,
    got_unsigned: object,
    got_ts: object,
    ev: EventArray,
    t0: int,
    t1: int,
    bins: int,
    tau: float,
) -> None:
    """Each torch output of one window against the numpy representation of the same window."""

    def host(t: object) -> np.ndarray:
        return t.cpu().numpy()  # type: ignore[attr-defined, no-any-return]

    assert_voxel_parity(
        host(got_vox),
        voxel_grid_bincount(ev, W, H, bins, t0, t1),
        host(got_vox_n),
        voxel_grid_bincount(ev, W, H, bins, t0, t1, normalize=True),
    )
    np.testing.assert_allclose(host(got_frame), event_frame(ev, W, H, t0, t1), rtol=RTOL, atol=ATOL)
    np.testing.assert_allclose(
        host(got_unsigned), event_frame(ev, W, H, t0, t1, signed=False), rtol=RTOL, atol=ATOL
    )
    np.testing.assert_allclose(host(got_ts), time_surface(ev, W, H, t0, t1, tau_us=tau), rtol=RTOL, atol=1e-6)


def check_batch(windows: list[tuple[EventArray, int, int]], bins: int, tau: float = 50.0) -> None:
    batch = on_device([pack_events(ev, W, H, t0, t1) for ev, t0, t1 in windows])
    vox, vox_n = tr.voxel_grid(batch, bins), tr.voxel_grid(batch, bins, normalize=True)
    frame, unsigned = tr.event_frame(batch), tr.event_frame(batch, signed=False)
    ts = tr.time_surface(batch, tau_us=tau)
    n = len(windows)
    assert tuple(vox.shape) == (n, bins, H, W)
    assert tuple(frame.shape) == (n, H, W)
    assert tuple(ts.shape) == (n, 2, H, W)
    assert str(vox.device).startswith(DEVICE)
    for i, (ev, t0, t1) in enumerate(windows):
        check_window(vox[i], vox_n[i], frame[i], unsigned[i], ts[i], ev, t0, t1, bins, tau)


@st.composite
def windows(draw: st.DrawFn) -> tuple[EventArray, int, int]:
    """A window [t0, t1] and events around it (some before, after, off the sensor)."""
    n = draw(st.integers(0, 120))
    t0 = draw(st.sampled_from([0, 12_345, BIG]))
    span = draw(st.sampled_from([0, 1, 9, 1000, 49_999]))
    seed = draw(st.integers(0, 2**16))
    rng = np.random.default_rng(seed)
    t = t0 + np.sort(rng.integers(-3, span + 4, n))
    ev = ev_of(rng.integers(0, W + 1, n), rng.integers(0, H + 1, n), rng.choice([-1, 1], n), t)
    return ev, t0, t0 + span


@pytest.mark.slow
@settings(max_examples=60, deadline=None)
@given(batch=st.lists(windows(), min_size=1, max_size=4), bins=st.sampled_from([1, 2, 5]))
def test_batches_match_numpy_window_by_window(batch: list[tuple[EventArray, int, int]], bins: int) -> None:
    check_batch(batch, bins)


def test_edge_cases() -> None:
    empty = (EventArray.empty(), BIG, BIG + 49_999)
    one_bin = (ev_of([0, 1, 1, 6], [0, 2, 2, 4], [1, -1, -1, 1], [BIG + 30] * 4), BIG, BIG + 49_999)
    last_us = (ev_of([3, 3, 2], [1, 1, 0], [1, 1, -1], [BIG, BIG + 49_999, BIG + 49_999]), BIG, BIG + 49_999)
    zero_length = (ev_of([1, 2], [1, 1], [1, -1], [BIG + 5, BIG + 5]), BIG + 5, BIG + 5)
    check_batch([empty, one_bin, last_us, zero_length, empty], bins=5)
    check_batch([empty], bins=5)
    # Events on the window's last microsecond go whole into the last bin; at one time, into one bin.
    batch = on_device([pack_events(ev, W, H, t0, t1) for ev, t0, t1 in (one_bin, last_us)])
    vox = tr.voxel_grid(batch, 5).cpu().numpy()
    assert vox[0, 0, 2, 1] == pytest.approx(-2 * (1 - 30 * 4 / 49_999), rel=1e-6)
    assert vox[1, 4, 1, 3] == 1
    assert vox[1, 4, 0, 2] == -1
    assert vox[1, 0, 1, 3] == 1
    assert vox[1, 1:4].sum() == 0
    # A time surface's reference time may be given; older than that fades, never above 1.
    ts = tr.time_surface(batch, tau_us=1000.0, t_ref_us=BIG + 60_000).cpu().numpy()
    np.testing.assert_allclose(
        ts[1],
        time_surface(last_us[0], W, H, BIG, BIG + 49_999, tau_us=1000.0, t_ref_us=BIG + 60_000),
        rtol=1e-6,
    )
    per_window = torch.tensor([BIG + 60_000, BIG + 60_000], device=DEVICE)
    np.testing.assert_array_equal(
        tr.time_surface(batch, tau_us=1000.0, t_ref_us=per_window).cpu().numpy(), ts
    )


def test_packing_counts_what_it_leaves_out() -> None:
    ev = ev_of([0, W, 1, 2], [0, 0, H, 1], [1, 1, -1, -1], [10, 20, 30, 500])
    packed = pack_events(ev, W, H, 0, 100)
    assert len(packed) == 1  # t=500 is outside the window: ignored, as the numpy functions do
    assert packed.off_sensor == 2  # inside the window but off the sensor: counted
    assert packed.pix.dtype == np.int32
    assert packed.dt.dtype == np.int32
    assert packed.nbytes == 9
    with pytest.raises(ValueError, match="int32"):
        pack_events(ev, W, H, 0, 2**31)
    with pytest.raises(ValueError, match="geometry"):
        concat_packed([packed, pack_events(ev, W + 1, H, 0, 100)])
    with pytest.raises(ValueError, match="bins"):
        tr.voxel_grid(on_device([packed]), 0)
    with pytest.raises(ValueError, match="tau"):
        tr.time_surface(on_device([packed]), tau_us=0.0)
