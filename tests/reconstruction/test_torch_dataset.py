"""The training reader: representations built on the device equal those built in the workers,
through real DataLoader workers, on a duck-typed take and on a simulated take.

The device is the CPU here; `RIGD_TEST_TORCH_DEVICE=cuda` builds them on a GPU
(`bench/gpu_check.sh`)."""

from __future__ import annotations

import functools
import os
import pickle
import subprocess
import sys
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from reconstruction.dataset import WindowSampler, torch_dataset
from reconstruction.representations import voxel_grid_bincount
from rigd.core.events import EventArray
from tests.reconstruction.parity import assert_voxel_parity

W, H = 40, 24
DEVICE = os.environ.get("RIGD_TEST_TORCH_DEVICE", "cpu")
T0 = 5_000_000_000  # a rig time far from 0


class FrameSeries:
    timestamps_us = T0 + np.arange(0, 1_000_000, 33_333, dtype=np.int64)

    def __getitem__(self, i: int) -> Any:
        return np.full((H, W), i, np.uint8)


class DenseTake:
    """Events spread over 1 s of a 40x24 sensor, a few off it; one 30 Hz camera."""

    def __init__(self, n: int = 40_000) -> None:
        rng = np.random.default_rng(1)
        self.ev = EventArray.from_arrays(
            rng.integers(0, W + 1, n),
            rng.integers(0, H, n),
            rng.choice([-1, 1], n),
            T0 + np.sort(rng.integers(0, 10**6, n)),
        )

    def sensor(self, name: str) -> DenseTake:  # its one sensor's events are the take's
        return self

    def events(self, t_start_us: int | None = None, t_end_us: int | None = None) -> EventArray:
        t = self.ev.t
        return self.ev[(t >= (t_start_us or 0)) & (t < (t_end_us or 2**62))]

    @property
    def geometry(self) -> tuple[int, int]:
        return W, H

    @property
    def span(self) -> tuple[int, int] | None:
        return int(self.ev.t[0]), int(self.ev.t[-1])

    def camera(self, name: str) -> FrameSeries:
        return FrameSeries()


def loader_batches(ds: Any, workers: int, batch_size: int = 4) -> list[dict[str, Any]]:
    torch = pytest.importorskip("torch")
    loader = torch.utils.data.DataLoader(
        ds, batch_size=batch_size, num_workers=workers, collate_fn=ds.collate, shuffle=False
    )
    out = []
    for b in loader:
        on_device = ds.to_device(b, DEVICE)
        key = next(k for k in ("voxels", "event_frame", "time_surface") if k in on_device)
        assert str(on_device[key].device).startswith(DEVICE)
        out.append({k: v.cpu() if hasattr(v, "cpu") else v for k, v in on_device.items()})
    return out


@pytest.mark.parametrize(
    ("representation", "key", "options"),
    [
        ("voxel_grid", "voxels", {"bins": 5}),
        ("voxel_grid", "voxels", {"bins": 3, "normalize": True}),
        ("event_frame", "event_frame", {}),
        ("event_frame", "event_frame", {"signed": False}),
        ("time_surface", "time_surface", {"tau_us": 5000.0}),
    ],
)
@pytest.mark.slow
def test_device_and_worker_representations_agree(
    representation: str, key: str, options: dict[str, Any]
) -> None:
    pytest.importorskip("torch")
    take = DenseTake()
    sampler = WindowSampler(take, "ev0", "cam0", window_us=50_000, bins=5, n_samples=10)
    opener = functools.partial(DenseTake)
    dev = torch_dataset(sampler, opener, representation=representation, representation_on="device", **options)
    wrk = torch_dataset(sampler, opener, representation=representation, representation_on="worker", **options)
    got, want = loader_batches(dev, workers=2), loader_batches(wrk, workers=0)
    assert len(got) == len(want) == 3  # 10 windows in batches of 4
    raw: list[tuple[Any, Any]] = [(None, None)] * 3
    if options.get("normalize"):  # which entries are zero is compared on the unnormalised grids
        plain = {**options, "normalize": False}
        raw = list(
            zip(
                loader_batches(torch_dataset(sampler, representation_on="device", **plain), 0),
                loader_batches(torch_dataset(sampler, representation_on="worker", **plain), 0),
                strict=True,
            )
        )
    for a, b, (ra, rb) in zip(got, want, raw, strict=True):
        assert a[key].shape == b[key].shape
        assert a[key].dtype == b[key].dtype
        if ra is None:
            np.testing.assert_allclose(a[key].numpy(), b[key].numpy(), rtol=1e-5, atol=1e-5)
        else:
            for i in range(a[key].shape[0]):
                assert_voxel_parity(
                    ra[key][i].numpy(), rb[key][i].numpy(), a[key][i].numpy(), b[key][i].numpy()
                )
        for k in ("t0_us", "t1_us", "frame_counts", "frame_times_us", "frames"):
            assert a[k].equal(b[k]), k
        assert (a["frame_counts"] >= 1).all()
        assert a["frames"].shape[0] == int(a["frame_counts"].sum())
        # The one sensor column past the edge is counted, not silently dropped.
        assert int(a["events_off_sensor"].sum()) > 0


def test_device_voxels_match_the_numpy_reference_of_each_window() -> None:
    pytest.importorskip("torch")
    take = DenseTake()
    sampler = WindowSampler(take, "ev0", None, window_us=20_000, bins=5, n_samples=6)
    ds = torch_dataset(sampler, representation_on="device")
    (batch,) = loader_batches(ds, workers=0, batch_size=6)
    assert batch["frames"].numel() == 0
    for i, (t0, t1) in enumerate(zip(batch["t0_us"].tolist(), batch["t1_us"].tolist(), strict=True)):
        ev = take.sensor("ev0").events(t0, t1)
        assert_voxel_parity(batch["voxels"][i].numpy(), voxel_grid_bincount(ev, W, H, 5, t0, t1 - 1))
    assert int(batch["events"].counts.sum()) == sum(
        int(((take.ev.t >= a) & (take.ev.t < b) & (take.ev.x < W)).sum())
        for a, b in zip(batch["t0_us"].tolist(), batch["t1_us"].tolist(), strict=True)
    )


def test_a_dataset_without_open_take_refuses_to_be_pickled_for_a_spawned_worker() -> None:
    pytest.importorskip("torch")
    sampler = WindowSampler(DenseTake(), "ev0", None, window_us=20_000, n_samples=2)
    with pytest.raises(TypeError, match="open_take"):
        pickle.dumps(torch_dataset(sampler))
    ds = pickle.loads(pickle.dumps(torch_dataset(sampler, functools.partial(DenseTake))))
    assert ds[0]["frames"].numel() == 0
    assert ds[1]["voxels"].shape == (5, H, W)


@pytest.mark.slow
def test_importing_the_packages_does_not_import_torch() -> None:
    code = (
        "import sys, rigd, rigd.take, reconstruction, reconstruction.dataset, "
        "reconstruction.representations, reconstruction.packed_events, reconstruction.voxel_kernel; "
        "assert 'torch' not in sys.modules, 'torch was imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.slow
def test_without_torch_the_dataset_says_how_to_install_it() -> None:
    code = (
        "import sys; sys.modules['torch'] = None\n"
        "from tests.reconstruction.test_torch_dataset import DenseTake\n"
        "from reconstruction.dataset import WindowSampler, torch_dataset\n"
        "s = WindowSampler(DenseTake(100), 'ev0', None, window_us=20_000, n_samples=2)\n"
        "try:\n    torch_dataset(s)\nexcept ImportError as e:\n    print(e)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        check=True,
        capture_output=True,
        text=True,
        cwd=Path(__file__).parents[2],
    )
    assert "pip install 'rigd[torch]'" in out.stdout


@pytest.mark.slow
def test_sim_take_through_device_workers(tmp_path: Path) -> None:
    """A take recorded on the simulator's virtual clock, read through two workers that each open
    it: the device-built voxels equal the reference on `take.sensor(name).events` of each window."""
    pytest.importorskip("torch")
    from rigd.app.capture import run_capture
    from rigd.app.config import default_sim_rig
    from rigd.take import Take

    cfg = default_sim_rig(
        world=f"tr-{uuid.uuid4().hex[:8]}", resolution=(160, 90), pixel_format="mono8", clock="virtual"
    )
    cfg.cameras = cfg.cameras[:1]
    path = run_capture(cfg, tmp_path, 1.0).path
    with Take(path) as take:
        sampler = WindowSampler(take, "ev0", "cam0", window_us=50_000, bins=5, n_samples=8)
        ds = torch_dataset(sampler, functools.partial(Take, path), representation_on="device")
        batches = loader_batches(ds, workers=2)
        assert sum(int(b["t0_us"].numel()) for b in batches) == 8
        total = 0
        for b in batches:
            assert int(b["events_off_sensor"].sum()) == 0
            for i, (t0, t1) in enumerate(zip(b["t0_us"].tolist(), b["t1_us"].tolist(), strict=True)):
                ev = take.sensor("ev0").events(t0, t1)
                total += len(ev)
                assert_voxel_parity(b["voxels"][i].numpy(), voxel_grid_bincount(ev, 160, 90, 5, t0, t1 - 1))
                times = take.camera("cam0").timestamps_us
                assert int(b["frame_counts"][i]) == int(((times >= t0) & (times < t1)).sum())
        assert total > 0
        assert int(sum(int(b["events"].counts.sum()) for b in batches)) == total
