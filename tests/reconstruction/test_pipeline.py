"""e2i, flow, partition, interpolation, metrics and losses on small synthetic scenes with ground truth."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from firmware_sim.testing.sprites import SpriteScene, linear_path, simulate, texture, translate
from reconstruction import losses
from reconstruction.e2i import METHODS as E2I_METHODS
from reconstruction.e2i import log_intensity, reconstruct
from reconstruction.flow import PRESETS, backward_warp, endpoint_error, flow
from reconstruction.interpolate import interpolate
from reconstruction.metrics import affine_align, motion_roi, psnr, psnr_roi, ssim
from reconstruction.partition import PartitionConfig, export_segments, load_segments, partition
from rigd.core.events import EventArray

pytestmark = pytest.mark.slow

W, H = 96, 72
C = 0.15


@pytest.fixture(scope="module")
def moving() -> tuple[SpriteScene, EventArray]:
    scene = SpriteScene(W, H, [linear_path(5, 10, 120, 40)], sprite_px=24, seed=2)
    return scene, simulate(scene, 0.0, 0.3, threshold=C, t_offset_us=10**10)


def test_e2i_methods_track_ground_truth(moving: tuple[SpriteScene, EventArray]) -> None:
    scene, ev = moving
    off = 10**10
    times = off + np.array([100_000, 200_000, 300_000])
    ftimes = off + np.arange(0, 300_001, 33_333)
    frames = [scene.render((t - off) * 1e-6) for t in ftimes]
    gt = [log_intensity(scene.render((t - off) * 1e-6)) for t in times]
    hold = log_intensity(frames[-1])
    for m in E2I_METHODS:
        snaps = reconstruct(
            ev,
            W,
            H,
            times,
            m,
            frames=frames,
            frame_times_us=ftimes,
            contrast=C,
            init_frame=frames[0],
            cutoff_hz=2.0,
        )
        assert np.isfinite(snaps).all()
        p = [psnr(affine_align(s, g), g, data_range=float(np.ptp(g))) for s, g in zip(snaps, gt, strict=True)]
        assert min(p) > 15, (m, p)
    del hold


def test_flow_presets_on_translation() -> None:
    img = texture(96, 128, seed=5)
    for dx, dy in [(1.5, -0.5), (4.0, 2.0)]:
        moved = translate(img, dx, dy)
        gt = np.broadcast_to(np.float32([dx, dy]), (96, 128, 2))
        inner = np.zeros((96, 128), bool)
        inner[16:-16, 16:-16] = True
        for preset in PRESETS:
            f = flow(img, moved, preset)
            assert endpoint_error(f, gt, inner) < 0.5, preset
        warped = backward_warp(moved, gt)
        assert psnr(warped[inner], img[inner]) > 30


def test_partition_static_one_segment_fast_part_more_segments() -> None:
    rng = np.random.default_rng(0)
    n = 2000  # noise only over 2 s
    noise = EventArray.from_arrays(
        rng.integers(0, W, n),
        rng.integers(0, H, n),
        rng.choice([-1, 1], n),
        np.sort(rng.integers(0, 2_000_000, n)),
    )
    cfg = PartitionConfig(window_us=10_000, threshold=1.0, min_segment_us=20_000)
    assert len(partition(noise, W, H, 0, 2_000_000, config=cfg)) == 1

    # slow for 0.5 s, then fast for 0.5 s
    def path(t: float) -> tuple[float, float]:
        return (10 + 30 * t, 20.0) if t < 0.5 else (25 + 300 * (t - 0.5) % 60, 20.0 + 20 * math.sin(20 * t))

    scene = SpriteScene(W, H, [path], sprite_px=20, seed=4)
    ev = simulate(scene, 0.0, 1.0, threshold=C)
    segs = partition(ev, W, H, 0, 1_000_000, config=cfg, candidate_times_us=np.arange(0, 1_000_000, 33_333))
    slow = [s for s in segs if s.t_end_us <= 500_000]
    fast = [s for s in segs if s.t_start_us >= 500_000]
    assert len(fast) > len(slow) >= 1
    assert np.mean([s.t_end_us - s.t_start_us for s in fast]) < np.mean(
        [s.t_end_us - s.t_start_us for s in slow]
    )
    for s in segs:
        assert s.t_start_us <= s.keyframe_us < s.t_end_us
    assert [s.t_end_us for s in segs[:-1]] == [s.t_start_us for s in segs[1:]]


def test_segments_roundtrip(tmp_path: Path) -> None:
    ev = EventArray.from_arrays([1], [1], [1], [5])
    segs = partition(ev, W, H, 0, 100_000)
    export_segments(segs, tmp_path / "s.json")
    assert load_segments(tmp_path / "s.json") == segs
    assert json.loads((tmp_path / "s.json").read_text())["segments"][0]["t_start_us"] == 0


def test_interpolation_events_beat_blend(moving: tuple[SpriteScene, EventArray]) -> None:
    scene, ev = moving
    off = 10**10
    t0, t, t1 = off + 100_000, off + 133_333, off + 166_666
    f0, f1, g = (scene.render((x - off) * 1e-6) for x in (t0, t, t1))
    f0, gt, f1 = scene.render(0.1), scene.render(0.133333), scene.render(0.166666)
    roi = motion_roi(np.stack([f0, gt, f1]))
    res = {
        m: psnr_roi(interpolate(f0, f1, t0, t1, t, m, events=ev, contrast=C), gt, roi)
        for m in ("nearest", "blend", "events")
    }
    assert res["events"] > res["blend"] + 3
    del g


def test_metrics_and_losses() -> None:
    img = texture(40, 50, seed=1)
    assert psnr(img, img) == 100.0
    assert ssim(img, img) == pytest.approx(1.0)
    assert ssim(img, img + 5) < 1.0
    assert losses.structure_ssim_loss(img / 255, img / 255 + 0.2) < 1e-6  # brightness-invariant
    assert losses.structure_ssim_loss(img / 255, texture(40, 50, seed=9) / 255) > 0.3
    assert losses.l1(img, img + 2) == pytest.approx(2.0)
    stack = np.stack([img, img, img])
    assert losses.spatiotemporal_tv(stack, beta=1.0) == pytest.approx(
        losses.spatiotemporal_tv(np.stack([img, img]), beta=1.0)
    )
    assert losses.spatiotemporal_tv(np.stack([img, img + 1])) > losses.spatiotemporal_tv(np.stack([img, img]))
    try:
        import torch  # noqa: F401
    except ImportError:
        with pytest.raises(ImportError, match="pip install"):
            losses.torch_losses()


def test_rigd_reconstruct_on_a_captured_sim_take(tmp_path: Path) -> None:
    """The batch command end to end: capture a take on the sim rig, then reconstruct it."""
    import json
    import uuid

    from typer.testing import CliRunner

    from rigd.app.capture import run_capture
    from rigd.app.cli import app
    from rigd.app.config import default_sim_rig

    cfg = default_sim_rig(world=f"rc-{uuid.uuid4().hex[:8]}", resolution=(160, 90), pixel_format="mono8")
    cfg.cameras = cfg.cameras[:1]
    take = run_capture(cfg, tmp_path, 1.0).path
    res = CliRunner().invoke(app, ["reconstruct", str(take), "--out", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "out" / take.stem / "segments.json").read_text())
    assert doc["segments"]
    assert doc["candidates"]["source"] == "cam0 mid-exposure"
    for sensor in ("ev0", "ev1"):
        assert doc["sensors"][sensor]["events_in"] > 0
        assert (tmp_path / "out" / take.stem / sensor / "snapshots.npz").stat().st_size > 0


def test_reconstruct_on_a_distributed_scheduler(tmp_path: Path) -> None:
    """`--scheduler ADDR`: the same batch through a dask.distributed cluster (in-process here)."""
    import uuid

    distributed = pytest.importorskip("distributed")
    from rigd.app.capture import run_capture
    from rigd.app.config import default_sim_rig
    from rigd.products.reconstruct import run_reconstruct
    from rigd.products.reconstruct_options import ReconstructOptions

    cfg = default_sim_rig(world=f"rd-{uuid.uuid4().hex[:8]}", resolution=(160, 90), pixel_format="mono8")
    cfg.cameras = cfg.cameras[:1]
    take = run_capture(cfg, tmp_path, 1.0).path
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
    ) as c:
        options = ReconstructOptions(takes=[take], out=tmp_path / "out", scheduler=c.scheduler_address)
        results = run_reconstruct(options)
    assert results[0].sensors["ev0"].events_in > 0
    assert (tmp_path / "out" / take.stem / "segments.json").exists()
    assert (tmp_path / "out" / take.stem / "ev0" / "snapshots.npz").exists()
