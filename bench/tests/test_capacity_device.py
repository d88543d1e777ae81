"""bench.capacity_device: its pieces, and one tiny level judged end to end (no timing asserts)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.capacity_device import (
    LevelSpec,
    camera_formats,
    disk_write_mbs,
    level_table,
    recording_density,
    run_level,
    source_take,
)
from rigd.evt import read_raw

RAW = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "events" / "evt3_gen41_sample.raw"
needs_data = pytest.mark.skipif(not RAW.is_file(), reason=f"shared test data not found at {RAW}")


@needs_data
def test_density_is_that_of_the_looped_periods() -> None:
    density, loop_us = recording_density(RAW)
    _, whole = read_raw(RAW)
    t0 = int(whole.events.t[0])
    assert loop_us == 8192
    assert density == np.count_nonzero(whole.events.t < t0 + 8192) / 8192
    assert 20 < density < 30  # events per us: the sample's ~25 Mev/s


def test_formats_fall_back_to_the_same_shape() -> None:
    assert camera_formats(["rgb8", "mono8"]) == ["rgb8", "mono8"]
    assert camera_formats(["no-such-format"]) == ["mono8"]


def test_disk_probe_writes_and_removes_its_file(tmp_path: Path) -> None:
    assert disk_write_mbs(tmp_path, 4) > 0
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
@needs_data
def test_a_slow_level_holds_and_accounts_for_every_event(tmp_path: Path) -> None:
    """Two file:// sensors at 0.5 Mev/s beside one small preloaded camera: whatever the
    sensors delivered is in the take or counted outside its window."""
    src = source_take(tmp_path, 2.0, "mono8", resolution=(64, 48))
    density, _ = recording_density(RAW)
    level = run_level(src, tmp_path, RAW, LevelSpec("slow", 0.02, 1, "mono8", 1.0), density, preload=2)
    assert level.produced_events > 0
    assert level.produced_events == level.outside_events + level.take_events
    assert level.produced_frames == level.outside_frames + level.take_frames > 0
    assert level.event_bytes > 0
    assert level.status_s
    assert level.rss_mb
    lines = level_table([level])
    assert "slow" in lines[2]
