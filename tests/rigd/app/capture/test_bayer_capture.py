"""A capture with bayer_rg8 cameras end to end: the take stores the raw RGGB mosaics as sent,
says so in its attrs, reads back as RGB, shows in `rigd inspect`, and replays as mosaics."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from firmware_sim.world import reset_world
from rigd.app.capture import run_capture
from rigd.app.cli import app
from rigd.app.config import default_sim_rig
from rigd.app.replay import replay_config
from rigd.app.service.thumbnails import frame_thumbnail
from rigd.core.pixels import demosaic
from rigd.take import open_take, validate_take

H, W = 90, 160


@pytest.fixture(scope="module")
def bayer_take(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    world = f"t-bayer-{uuid.uuid4().hex[:8]}"
    cfg = default_sim_rig(world=world, resolution=(W, H), pixel_format="bayer_rg8", clock="virtual")
    res = run_capture(cfg, tmp_path_factory.mktemp("bayer"), 0.5)
    yield res.path
    reset_world(world)


@pytest.mark.slow
def test_take_stores_the_mosaics_with_what_they_are(bayer_take: Path) -> None:
    assert validate_take(bayer_take) == []
    with h5py.File(bayer_take, "r") as f:
        for cam in ("cam0", "cam1", "cam2"):
            g = f[f"frames/{cam}"]
            assert g["images"].dtype == np.uint8
            assert g["images"].shape[1:] == (H, W)
            assert g["images"].shape[0] >= 14  # 0.5 s at 30 Hz
            assert g.attrs["pixel_format"] == "bayer_rg8"
            assert g.attrs["bayer_pattern"] == "RGGB"
            assert g.attrs["channels"] == 1


def test_take_reads_back_as_rgb(bayer_take: Path) -> None:
    with open_take(bayer_take) as take:
        fs = take.camera("cam0")
        assert fs.pixel_format == "bayer_rg8"
        assert fs.bayer_pattern == "RGGB"
        assert fs.stored_shape == (H, W)
        assert fs.shape == (H, W, 3)
        frame = fs[len(fs) // 2]
        assert frame.image.shape == (H, W, 3)
        assert frame.pixel_format == "rgb8"
        raw = fs.raw(len(fs) // 2)
        assert raw.shape == (H, W)
        np.testing.assert_array_equal(frame.image, demosaic(raw))
        np.testing.assert_array_equal(fs.rgb(0), fs[0].image)
        assert fs.gray(0).shape == (H, W)
        as_stored = take.camera("cam0", demosaic=False)
        assert as_stored.shape == (H, W)
        np.testing.assert_array_equal(as_stored[1].image, fs.raw(1))
        assert as_stored[1].pixel_format == "bayer_rg8"
        # The take's preview (console) is an RGB JPEG of the full-colour frame.
        jpeg, w, h = frame_thumbnail(frame, 80)
        assert (w, h) == (80, 45)
        assert jpeg[:2] == b"\xff\xd8"
        summary = take.summary()
    assert summary.cameras["cam0"].pixel_format == "bayer_rg8"
    assert summary.cameras["cam0"].shape == [H, W]


@pytest.mark.slow
def test_inspect_shows_the_pixel_format(bayer_take: Path, tmp_path: Path) -> None:
    runner = CliRunner()
    r = runner.invoke(app, ["inspect", str(bayer_take)], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    assert "bayer_rg8" in r.output
    sheet = tmp_path / "sheet.png"
    r = runner.invoke(app, ["inspect", str(bayer_take), "--thumbnails", str(sheet)])
    assert r.exit_code == 0, r.output
    assert sheet.stat().st_size > 1000


@pytest.mark.slow
def test_replay_delivers_the_recorded_mosaics(bayer_take: Path, tmp_path: Path) -> None:
    config, duration = replay_config(bayer_take, clock="virtual")
    try:
        result = run_capture(config, tmp_path, duration)
    finally:
        reset_world(f"replay:{bayer_take.resolve()}")
    with open_take(bayer_take) as a, open_take(result.path) as b:
        fa, fb = a.camera("cam1", demosaic=False), b.camera("cam1", demosaic=False)
        assert fb.pixel_format == "bayer_rg8"
        assert len(fa) == len(fb) > 0
        for i in range(len(fa)):
            np.testing.assert_array_equal(fa[i].image, fb[i].image)
