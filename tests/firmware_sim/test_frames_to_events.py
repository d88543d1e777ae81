"""Sub-stepping, streaming, frame readers and take output of the frames-to-events pipeline."""

from __future__ import annotations

import tracemalloc
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from firmware_sim.event_model import PixelModelConfig
from firmware_sim.frame_sources import array_source, folder_source, open_source, take_source, video_source
from firmware_sim.frames_to_events import EVENT_SENSOR_NAME, FramesToEvents, simulate_to_take, to_gray
from rigd.core.devices import DeviceInfo
from rigd.core.events import EventArray
from rigd.core.frames import Frame
from rigd.core.schema import SyncReport
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.take import TakeWriter, open_take, validate_take
from rigd.take.seal import finalize_take

W, H = 96, 64


def bar_frame(x: float, w: int = W, h: int = H) -> np.ndarray:
    """A bright 6 px vertical bar with soft edges at x on a dark background (uint8)."""
    cols = np.arange(w, dtype=np.float32)
    prof = np.clip(3.5 - np.abs(cols - x), 0.0, 1.0)
    return np.repeat((30 + 200 * prof)[None, :], h, axis=0).astype(np.uint8)


def texture(seed: int = 0, w: int = W, h: int = H, margin: int = 200) -> np.ndarray:
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (h, w + margin)).astype(np.float32), (0, 0), 2.0)
    return np.clip((tex - tex.mean()) * 5 + 128, 0, 255).astype(np.float32)


def shifted(tex: np.ndarray, dx: float, w: int = W) -> np.ndarray:
    m = np.float32([[1, 0, dx], [0, 1, 0]])
    return cv2.warpAffine(tex, m, (w, tex.shape[0]), flags=cv2.INTER_LINEAR).astype(np.uint8)


def square_frame(x: float, patch: np.ndarray) -> np.ndarray:
    """A textured square with top-left corner at (x, 20) on a uniform gray background."""
    img = np.full((H, W), 128.0, np.float32)
    m = np.float32([[1, 0, x], [0, 1, 20]])
    mask = cv2.warpAffine(np.ones_like(patch), m, (W, H), flags=cv2.INTER_LINEAR)
    moved = cv2.warpAffine(patch, m, (W, H), flags=cv2.INTER_LINEAR)
    return np.clip(img * (1 - mask) + moved, 0, 255).astype(np.uint8)


def test_one_fps_fast_motion_substeps_and_events_follow_the_motion() -> None:
    speed, side = 20.0, 24  # px per frame at 1 FPS; square side
    patch = texture(4)[:side, :side]
    f2e = FramesToEvents(W, H, max_px_per_step=1.0)
    results = [f2e.push(square_frame(5 + speed * i, patch), 1_000_000 * i) for i in range(4)]
    assert all(r.n_substeps >= 18 for r in results[1:])
    assert all(r.motion_px == pytest.approx(speed, rel=0.4) for r in results[1:])
    ev = EventArray.concatenate([r.events for r in results])
    assert ev.is_time_sorted()
    ev = ev[ev.t < 3_000_000]
    # The events of each 100 ms window are where the square is then, not where a frame left it.
    bins = (ev.t // 100_000).astype(np.int64)
    centre = np.bincount(bins, weights=ev.x.astype(np.float64)) / np.maximum(np.bincount(bins), 1)
    t_mid = (np.arange(centre.size) + 0.5) * 0.1
    expected = 5 + speed * t_mid + side / 2
    filled = np.bincount(bins) > 20
    assert filled.sum() >= 25
    assert np.abs(centre - expected)[filled].max() < 5


def test_without_substeps_events_stay_between_frames() -> None:
    f2e = FramesToEvents(W, H, substeps=1)
    results = [f2e.push(bar_frame(10 + 20 * i), 1_000_000 * i) for i in range(3)]
    assert [r.n_substeps for r in results] == [0, 1, 1]
    assert np.isnan(results[1].motion_px)


def test_fixed_substeps_are_used_and_times_are_inside_the_pair() -> None:
    f2e = FramesToEvents(W, H, substeps=5)
    tex = texture()
    f2e.push(shifted(tex, 0), 0)
    r = f2e.push(shifted(tex, -4), 40_000)
    assert r.n_substeps == 5
    assert len(r.events) > 0
    assert r.events.is_time_sorted()
    assert r.events.t.min() > 0
    assert r.events.t.max() <= 40_000


def test_slow_motion_and_identical_frames_need_no_substeps() -> None:
    tex = texture(1)
    f2e = FramesToEvents(W, H, max_px_per_step=1.0)
    f2e.push(shifted(tex, 0), 0)
    assert f2e.push(shifted(tex, -0.4), 10_000).n_substeps == 1
    same = f2e.push(shifted(tex, -0.4), 20_000)
    assert same.n_substeps == 1
    assert len(same.events) == 0


def test_substeps_capped_by_time_resolution() -> None:
    f2e = FramesToEvents(W, H, substeps=8)
    f2e.push(bar_frame(10), 0)
    assert f2e.push(bar_frame(30), 3).n_substeps == 3


def test_uint16_and_colour_inputs_match_uint8_gray() -> None:
    tex = texture(2)
    frames = [shifted(tex, -3.0 * i) for i in range(3)]
    runs = []
    for conv in (lambda f: f, lambda f: f.astype(np.uint16) * 257, lambda f: np.dstack([f, f, f])):
        f2e = FramesToEvents(W, H, substeps=3)
        runs.append(
            EventArray.concatenate([f2e.push(conv(f), i * 10_000).events for i, f in enumerate(frames)])
        )
    assert len(runs[0]) > 100
    for other in runs[1:]:
        assert abs(len(other) - len(runs[0])) <= 0.01 * len(runs[0])


def test_resize_and_bad_frames() -> None:
    f2e = FramesToEvents(48, 32, substeps=1)
    r = f2e.push(bar_frame(10), 0)
    assert r.index == 0
    with pytest.raises(ValueError, match="frame 1: shape"):
        f2e.push(np.zeros((H, W, 2), np.uint8), 10)
    with pytest.raises(ValueError, match="either substeps or max_px_per_step"):
        FramesToEvents(W, H, substeps=2, max_px_per_step=1.0)
    assert to_gray(np.zeros((H, W, 4), np.uint8), 0, (20, 10)).shape == (10, 20)


@pytest.mark.slow
def test_streaming_uses_constant_memory() -> None:
    tex = texture(3, margin=600)

    def frames() -> Iterator[tuple[np.ndarray, int]]:
        for i in range(500):
            yield shifted(tex, -1.5 * abs(i % 400 - 200)), 5_000 * i

    f2e = FramesToEvents(W, H, max_px_per_step=1.0)
    tracemalloc.start()
    try:
        n_events = 0
        for r in f2e.run(frames()):
            n_events += len(r.events)
            if r.index == 100:
                base = tracemalloc.get_traced_memory()[0]
        grown = tracemalloc.get_traced_memory()[0] - base
    finally:
        tracemalloc.stop()
    assert n_events > 10_000
    assert 2 <= f2e.substeps_max <= 6
    assert grown < 200_000


def write_rgb_take(path: Path, frames: list[np.ndarray], dt_us: int) -> None:
    w = TakeWriter(path, rig_config_json="{}", take_id="src", config=WriterConfig(), rigd_version="t")
    h, wd = frames[0].shape[:2]
    w.add_camera("cam1", DeviceInfo(kind="rgb_camera", spec="test"), (h, wd, 3), np.uint8, "{}")
    for i, f in enumerate(frames):
        w.append_frame("cam1", Frame(np.dstack([f, f, f]), 1_000 + i * dt_us, 100, i, 0))
    report = SyncReport(rate_hz=0.0, n_pulses=0, t_first_pulse_us=None, t_last_pulse_us=None)
    finalize_take(w, {"cam1": ClockMap.identity()}, {}, report)
    w.close()


def test_inputs_arrays_folder_video_take(tmp_path: Path) -> None:
    frames = [bar_frame(10 + 3 * i) for i in range(6)]
    arr = list(array_source(np.stack(frames), fps=100.0).frames)
    assert [t for _, t in arr] == [0, 10_000, 20_000, 30_000, 40_000, 50_000]
    folder = tmp_path / "imgs"
    folder.mkdir()
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / f"{i:04d}.png"), f)
    (folder / "notes.txt").write_text("ignored")
    got = list(folder_source(folder, fps=100.0).frames)
    assert len(got) == 6
    np.testing.assert_array_equal(to_gray(got[3][0], 3), frames[3])
    take = tmp_path / "src.h5"
    write_rgb_take(take, frames, 10_000)
    src = open_source(take)
    got_take = list(src.frames)
    assert [t for _, t in got_take] == [1_000 + 10_000 * i for i in range(6)]
    assert src.fps == pytest.approx(100.0)
    with pytest.raises(ValueError, match="no camera 'nope'"):
        take_source(take, camera="nope")
    video = tmp_path / "v.avi"
    vw = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (W, H))
    if not vw.isOpened():
        pytest.skip("no MJPG video writer in this OpenCV build")
    for f in frames:
        vw.write(cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))
    vw.release()
    vs = video_source(video)
    vid = list(vs.frames)
    assert vs.fps == pytest.approx(25.0)
    assert len(vid) == 6
    assert vid[1][1] == 40_000
    with pytest.raises(ValueError, match="pass --fps"):
        open_source(folder)


@pytest.mark.slow
def test_simulate_to_take_roundtrip(tmp_path: Path) -> None:
    frames = [bar_frame(10 + 8 * i) for i in range(6)]
    cfg = PixelModelConfig(sigma=0.02, seed=3)
    direct = list(FramesToEvents(W, H, cfg, max_px_per_step=1.0).run(array_source(frames, fps=50.0).frames))
    expected = EventArray.concatenate([r.events for r in direct])
    out = tmp_path / "sim.h5"
    seen: list[int] = []
    summary = simulate_to_take(
        array_source(frames, fps=50.0),
        out,
        FramesToEvents(W, H, cfg, max_px_per_step=1.0),
        with_frames=True,
        on_step=lambda r: seen.append(r.n_substeps),
    )
    assert summary.frames == 6
    assert summary.events == len(expected) > 0
    assert seen == [r.n_substeps for r in direct]
    assert min(seen[1:]) >= 2
    with open_take(out) as take:
        assert take.status == "complete"
        ev = take.sensor(EVENT_SENSOR_NAME).events()
        np.testing.assert_array_equal(ev.t, expected.t)
        np.testing.assert_array_equal(ev.x, expected.x)
        np.testing.assert_array_equal(ev.p, expected.p)
        assert len(take.camera("cam0")) == 6
        assert take.camera("cam0").timestamps_us[1] == 20_000
        assert take.config["simulator"]["pixel_model"]["sigma"] == 0.02
    assert validate_take(out) == []
