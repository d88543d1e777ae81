"""`rigd reconstruct`'s workflow on small takes: block-wise results equal whole-stream ones, one
rig-level segmentation, keyframes among the RGB mid-exposure times, the same output on every
scheduler, progress in events."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from firmware_sim.testing.takes import make_take
from reconstruction.filters import background_activity_filter
from reconstruction.partition import (
    PartitionConfig,
    canonical_keyframe_bruteforce,
    interval_maps,
    segment_starts,
    window_counts,
)
from rigd.app.cli import app
from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.events import EventArray
from rigd.core.frames import Frame
from rigd.core.progress import ProgressUpdate
from rigd.core.schema import SyncReport
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.products.reconstruct import (
    STAGE_FILTER,
    STAGE_MAPS,
    STAGE_SNAPSHOTS,
    reconstruct_take,
    run_reconstruct,
)
from rigd.products.reconstruct_options import ReconstructOptions
from rigd.products.reconstruct_tasks import FilterKnobs
from rigd.take import TakeWriter
from rigd.take.reader import Take
from rigd.take.seal import finalize_take

pytestmark = pytest.mark.slow

W, H = 96, 64
PERIOD_US = 33_333
EXPOSURE_US = 8_000


def bar_sweeps(sweeps: list[tuple[int, int]], seed: int = 0) -> EventArray:
    """A vertical bar sweeping the sensor once per (start us, duration us): every pixel of a column
    fires within 10 us of the others, so the paper's filter keeps them."""
    rng = np.random.default_rng(seed)
    parts = []
    for t0, dur in sweeps:
        col_t = t0 + (np.arange(W) * dur) // W
        xs, ys = np.meshgrid(np.arange(W), np.arange(H))
        t = col_t[xs.ravel()] + rng.integers(0, 10, xs.size)
        parts.append((xs.ravel(), ys.ravel(), np.ones(xs.size, np.int64), t))
    x, y, p, t = (np.concatenate(c) for c in zip(*parts, strict=True))
    order = np.argsort(t, kind="stable")
    return EventArray.from_arrays(x[order], y[order], p[order], t[order])


def noise(n: int, t0: int, t1: int, seed: int) -> EventArray:
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(t0, t1, n))
    return EventArray.from_arrays(rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, 2, n), t)


def by_time(*parts: EventArray) -> EventArray:
    ev = EventArray.concatenate(list(parts))
    return ev[np.argsort(ev.t, kind="stable")]


def write_take(path: Path, events: dict[str, EventArray], span_us: int, *, block: int = 1024) -> Path:
    """A finalized take (identity clocks) with cam0 at 30 Hz over the span and the given sensors."""
    cfg = WriterConfig(event_compression="lz4", event_chunk=block, fsync=False)
    w = TakeWriter(path, rig_config_json="{}", take_id=path.stem, config=cfg, rigd_version="t")
    w.add_trigger(DeviceInfo(kind="trigger", spec="sim://t/trigger"))
    w.add_camera("cam0", DeviceInfo(kind="rgb_camera", spec="sim://t/cam0"), (8, 8), np.uint8, "{}")
    for name in events:
        w.add_event_sensor(name, DeviceInfo(kind="event_sensor", spec=f"sim://t/{name}"), W, H, "{}")
    for name, ev in events.items():
        w.append_events(name, ev)
    frame_t = np.arange(0, span_us, PERIOD_US, dtype=np.int64)
    for i, t in enumerate(frame_t):
        w.append_frame("cam0", Frame(np.zeros((8, 8), np.uint8), int(t), EXPOSURE_US, i, i))
    n = len(frame_t)
    w.append_pulses(PulseBatch(np.arange(n, dtype=np.int64), frame_t, np.arange(n, dtype=np.int64)))
    maps = {d: ClockMap(0, 0) for d in ["cam0", *events]}
    report = SyncReport(rate_hz=30.0, n_pulses=n, t_first_pulse_us=0, t_last_pulse_us=int(frame_t[-1]))
    finalize_take(w, maps, {"cam0": np.arange(n, dtype=np.int64)}, report)
    w.close()
    return path


SPAN = 1_000_000


@pytest.fixture(scope="module")
def moving_take(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two sensors: fast sweeps in two bursts and background noise; the second sensor sees them later."""
    d = tmp_path_factory.mktemp("rec")
    sweeps = [(100_000 + k * 12_000, 8_000) for k in range(8)] + [
        (600_000 + k * 12_000, 8_000) for k in range(8)
    ]
    ev0 = by_time(bar_sweeps(sweeps, 1), noise(20_000, 0, SPAN, 2))
    ev1 = by_time(bar_sweeps([(t + 3_000, d) for t, d in sweeps], 3), noise(20_000, 0, SPAN, 4))
    return write_take(d / "moving.h5", {"ev0": ev0, "ev1": ev1}, SPAN)


def options(tmp: Path, **kw: object) -> ReconstructOptions:
    return ReconstructOptions(takes=[], out=tmp, scheduler="sync", block_events=4096, **kw)


def test_blocks_give_the_whole_stream_result(moving_take: Path, tmp_path: Path) -> None:
    """Kept counts and segments from 4096-event blocks equal one pass of the filter over each stream."""
    r = reconstruct_take(moving_take, options(tmp_path))
    cfg = PartitionConfig()
    counts = None
    with Take(moving_take) as take:
        t0 = min(take.sensor(s).span[0] for s in ("ev0", "ev1"))  # type: ignore[index]
        t1 = max(take.sensor(s).span[1] for s in ("ev0", "ev1")) + 1  # type: ignore[index]
        for s in ("ev0", "ev1"):
            kept = background_activity_filter(take.sensor(s).events(), W, H)
            assert r.sensors[s].events_kept == len(kept)
            assert r.sensors[s].events_in == take.sensor(s).count
            c = window_counts(kept, t0, t1, cfg.window_us)
            counts = c if counts is None else counts + c
    doc = json.loads((tmp_path / "moving" / "segments.json").read_text())
    starts = segment_starts(np.asarray(counts), 2 * W * H, cfg)
    assert [s["t_start_us"] for s in doc["segments"]] == [t0 + k * cfg.window_us for k in starts]
    assert r.segments == len(starts) >= 3  # the two bursts cut the sequence; the noise alone does not


def test_keyframes_are_the_brute_force_argmin_over_mid_exposures(moving_take: Path, tmp_path: Path) -> None:
    reconstruct_take(moving_take, options(tmp_path))
    doc = json.loads((tmp_path / "moving" / "segments.json").read_text())
    assert doc["candidates"]["source"] == "cam0 mid-exposure"
    mids = np.arange(0, SPAN, PERIOD_US, dtype=np.int64) + EXPOSURE_US // 2
    with Take(moving_take) as take:
        kept = {s: background_activity_filter(take.sensor(s).events(), W, H) for s in ("ev0", "ev1")}
    checked = 0
    for seg in doc["segments"]:
        a, b = seg["t_start_us"], seg["t_end_us"]
        taus = mids[(mids >= a) & (mids < b)]
        if len(taus) == 0:
            assert seg["keyframe_us"] == a
            continue
        cuts = np.concatenate([[a], taus, [b]]).astype(np.int64)
        cuts = np.unique(cuts)
        maps = []
        for s in ("ev0", "ev1"):
            inc = interval_maps(kept[s], W, H, cuts, 0.25)
            acc = np.concatenate([np.zeros((1, *inc.shape[1:]), np.int64), np.cumsum(inc, axis=0)])
            maps.append(acc[np.searchsorted(cuts, taus)].reshape(len(taus), -1))
        expect = taus[canonical_keyframe_bruteforce(np.concatenate(maps, axis=1).astype(np.float64))]
        assert seg["keyframe_us"] == expect
        checked += 1
    assert checked >= 3


def test_every_scheduler_writes_the_same(moving_take: Path, tmp_path: Path) -> None:
    outs = {}
    for sched in ("sync", "threads", "processes"):
        o = ReconstructOptions(
            takes=[moving_take], out=tmp_path / sched, scheduler=sched, workers=2, block_events=8192
        )
        (r,) = run_reconstruct(o)
        assert r.error is None
        doc = json.loads((tmp_path / sched / "moving" / "segments.json").read_text())
        with np.load(tmp_path / sched / "moving" / "ev1" / "snapshots.npz") as z:
            outs[sched] = (doc["segments"], z["times_us"].tolist(), z["log_intensity"].copy())
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        o = ReconstructOptions(
            takes=[moving_take], out=tmp_path / "dist", scheduler=cluster.scheduler_address
        )
        (r,) = run_reconstruct(o.model_copy(update={"block_events": 8192}))
        assert r.error is None
    doc = json.loads((tmp_path / "dist" / "moving" / "segments.json").read_text())
    with np.load(tmp_path / "dist" / "moving" / "ev1" / "snapshots.npz") as z:
        outs["distributed"] = (doc["segments"], z["times_us"].tolist(), z["log_intensity"].copy())
    ref = outs["sync"]
    for sched, got in outs.items():
        assert got[0] == ref[0], sched
        assert got[1] == ref[1] == [s["keyframe_us"] for s in ref[0]], sched
        np.testing.assert_array_equal(got[2], ref[2], err_msg=sched)


def test_static_scene_is_one_segment(tmp_path: Path) -> None:
    path = write_take(tmp_path / "still.h5", {"ev0": noise(50_000, 0, SPAN, 7)}, SPAN)
    r = reconstruct_take(path, options(tmp_path))
    assert r.segments == 1
    assert r.sensors["ev0"].events_kept < 0.05 * r.sensors["ev0"].events_in  # noise has no support


def test_unfiltered_noise_fills_the_budget(tmp_path: Path) -> None:
    """Without the filter the same noise is activity: the knob changes what the partition sees."""
    path = write_take(tmp_path / "still.h5", {"ev0": noise(50_000, 0, SPAN, 7)}, SPAN)
    r = reconstruct_take(path, options(tmp_path, filter=FilterKnobs(enabled=False), threshold=1.0))
    assert r.sensors["ev0"].events_kept == 50_000
    assert r.segments >= 5  # 50k events on 6144 px: 8 per px against a budget of 1


def test_progress_counts_events_per_stage(moving_take: Path, tmp_path: Path) -> None:
    updates: list[ProgressUpdate] = []
    o = ReconstructOptions(
        takes=[moving_take], out=tmp_path, scheduler="threads", workers=2, block_events=4096
    )
    (r,) = run_reconstruct(o, updates.append)
    n = sum(s.events_in for s in r.sensors.values())
    for stage in (STAGE_FILTER, STAGE_MAPS):
        mine = [u for u in updates if u.stage == stage]
        assert mine[0].done == 0
        assert mine[-1].done == mine[-1].total
        assert [u.done for u in mine] == sorted(u.done or 0 for u in mine)
        assert len(mine) > 10
    assert [u for u in updates if u.stage == STAGE_FILTER][-1].total == n
    assert {u.unit for u in updates if u.stage != STAGE_SNAPSHOTS} == {"events"}
    snaps = [u for u in updates if u.stage == STAGE_SNAPSHOTS]
    assert snaps[-1].done == snaps[-1].total == 2 * r.segments


def test_highpass_snapshot_matches_integrating_the_whole_stream(moving_take: Path, tmp_path: Path) -> None:
    """The windowed high-pass snapshot differs from one over the whole history by < 1e-3 log units."""
    from reconstruction.e2i import reconstruct

    reconstruct_take(moving_take, options(tmp_path))
    with np.load(tmp_path / "moving" / "ev0" / "snapshots.npz") as z:
        times, snaps = z["times_us"], z["log_intensity"]
    with Take(moving_take) as take:
        kept = background_activity_filter(take.sensor("ev0").events(), W, H)
    full = reconstruct(kept, W, H, times, "highpass", contrast=0.3, cutoff_hz=5.0)
    assert np.abs(full - snaps).max() < 1e-3


def test_cli_knobs_and_summary_line(moving_take: Path, tmp_path: Path) -> None:
    r = CliRunner().invoke(
        app,
        [
            "reconstruct",
            str(moving_take),
            "--out",
            str(tmp_path),
            "--scheduler",
            "sync",
            "--filter-window-us",
            "1000",
        ],
    )
    assert r.exit_code == 0, r.output
    (line,) = r.output.strip().splitlines()  # off a terminal and without -v: the summary alone
    assert line.startswith(f"{moving_take}: ")
    assert "segments" in line
    assert "ev0 kept" in line
    assert "Mev/s" in line
    doc = json.loads((tmp_path / "moving" / "segments.json").read_text())
    assert doc["options"]["filter"]["window_us"] == 1000
    # a picture of it, as inspect --thumbnails gives of a take: the rate plot, a row per sensor
    import cv2

    from rigd.products.reconstruct_picture import PLOT_HEIGHT, WIDTH

    pic = cv2.imread(str(tmp_path / "moving" / "overview.png"))
    assert pic is not None
    assert pic.shape[1] == WIDTH
    assert pic.shape[0] > PLOT_HEIGHT + 20 * len(doc["sensors"])
    row = pic[PLOT_HEIGHT + 20 :]
    assert row.std() > 5  # snapshots drawn, not an empty band
    wide = doc["sensors"]["ev0"]["events_kept"]
    narrow = reconstruct_take(moving_take, options(tmp_path / "n")).sensors["ev0"].events_kept
    assert wide > narrow  # a longer window supports more of the noise


def test_unknown_keyframe_camera_is_one_line(moving_take: Path, tmp_path: Path) -> None:
    r = CliRunner().invoke(
        app, ["reconstruct", str(moving_take), "--out", str(tmp_path), "--keyframe-camera", "cam7"]
    )
    assert r.exit_code == 1
    (line,) = r.output.strip().splitlines()
    assert "cam7" in line
    assert "cam0" in line
    assert str(moving_take) in line


def test_old_style_take_still_reconstructs(tmp_path: Path) -> None:
    path = make_take(tmp_path / "t.h5", n_events=60_000).path
    (r,) = run_reconstruct(ReconstructOptions(takes=[path], out=tmp_path / "out"))
    assert r.error is None
    assert r.sensors["ev0"].events_in == 60_000
    doc = json.loads((tmp_path / "out" / "take-1" / "segments.json").read_text())
    assert len(doc["segments"]) == r.segments > 0
    with np.load(tmp_path / "out" / "take-1" / "ev0" / "snapshots.npz") as snaps:
        assert snaps["log_intensity"].shape[0] == r.segments
        assert snaps["times_us"].dtype == np.int64


@pytest.mark.parametrize(
    ("args", "flag"),
    [
        (["--threshold", "0"], "--threshold"),
        (["--filter-support", "99"], "--filter-support"),
        (["--e2i", "e2vid"], "--e2i"),
        (["--cutoff-hz", "0"], "--cutoff-hz"),
    ],
)
def test_bad_knob_is_one_line_naming_the_flag(
    moving_take: Path, tmp_path: Path, args: list[str], flag: str
) -> None:
    r = CliRunner().invoke(app, ["reconstruct", str(moving_take), "--out", str(tmp_path / "o"), *args])
    assert r.exit_code == 2, r.output
    (line,) = r.output.strip().splitlines()
    assert line.startswith(f"error: {flag}")
    assert not (tmp_path / "o").exists()


def test_snapshot_file_streams_and_leaves_nothing_half_written(tmp_path: Path) -> None:
    from rigd.core.errors import RigdError
    from rigd.products.reconstruct import _SnapshotFile

    path = tmp_path / "s" / "snapshots.npz"
    images = np.random.default_rng(0).normal(size=(3, 4, 5)).astype(np.float32)
    with _SnapshotFile(path, 3, 4, 5) as f:
        for i, im in enumerate(images):
            f.append(10 * i, im)
    with np.load(path) as z:
        np.testing.assert_array_equal(z["log_intensity"], images)
        assert z["times_us"].tolist() == [0, 10, 20]
    bad = tmp_path / "b" / "snapshots.npz"

    def wrong_shape() -> None:
        with _SnapshotFile(bad, 2, 4, 5) as f:
            f.append(0, images[0])
            f.append(1, np.zeros((5, 4), np.float32))

    def too_few() -> None:
        with _SnapshotFile(bad, 2, 4, 5) as f:
            f.append(0, images[0])

    with pytest.raises(RigdError, match="does not fit"):
        wrong_shape()
    with pytest.raises(RigdError, match="1 of 2 snapshots"):
        too_few()
    assert list(bad.parent.iterdir()) == []


def test_many_segments_one_snapshot_each(moving_take: Path, tmp_path: Path) -> None:
    o = options(tmp_path, filter=FilterKnobs(enabled=False), threshold=0.2)
    r = reconstruct_take(moving_take, o)
    assert r.segments > 20
    doc = json.loads((tmp_path / "moving" / "segments.json").read_text())
    for s in ("ev0", "ev1"):
        with np.load(tmp_path / "moving" / s / "snapshots.npz") as z:
            assert z["log_intensity"].shape == (r.segments, H, W)
            assert z["times_us"].tolist() == [seg["keyframe_us"] for seg in doc["segments"]]
