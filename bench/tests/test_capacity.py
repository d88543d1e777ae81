"""bench.capacity: its microbenchmark stages (bench.capacity_micro) run on a tiny input (no timing
asserts)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.capacity import device_drops
from bench.capacity_micro import (
    MicroResult,
    Stage,
    ceiling_table,
    decode_buffers,
    encode_slices,
    frame_writes,
    micro_events,
    slices,
)
from rigd.core.events import EventArray
from rigd.core.frames import Frame


def _events(n: int = 20_000) -> EventArray:
    rng = np.random.default_rng(1)
    t = np.sort(rng.integers(0, 50_000, n))
    return EventArray.from_arrays(rng.integers(0, 64, n), rng.integers(0, 48, n), rng.integers(0, 2, n), t)


def test_evt3_round_trip_through_slices() -> None:
    ev = _events()
    parts = slices(ev)
    assert sum(len(p) for p in parts) == len(ev)
    decoded = EventArray.concatenate(decode_buffers(encode_slices(parts), 64, 48))
    for k in "txyp":
        assert np.array_equal(getattr(decoded, k), getattr(ev, k)), k


def test_micro_stages_and_ceiling(tmp_path: Path) -> None:
    stages, bytes_per_event, ratio = micro_events(_events(), 64, 48, tmp_path, repeat=1, chunk=4096)
    names = [s.name for s in stages]
    assert any(n.startswith("EVT3 decode") for n in names)
    assert any(n.startswith("EventSink append, LZ4+shuffle, disk") for n in names)
    assert all(s.median > 0 for s in stages)
    assert 0 < bytes_per_event < 16
    assert 0 < ratio <= 1.5
    assert not list(tmp_path.iterdir())  # the sink files are removed

    img = np.zeros((8, 16, 3), np.uint8)
    frame_writes([Frame(img, 0, 100, 0, 0, 0)], 5, {}, tmp_path / "f.h5")
    assert not (tmp_path / "f.h5").exists()

    stages += [
        Stage("take read, events", "source", "Mev/s", 50.0, 60.0),
        Stage("take read, frames", "source", "MB/s", 900.0, 1000.0),
        Stage("CameraSink frame writes", "capture", "MB/s", 500.0, 600.0),
    ]
    lines = ceiling_table(MicroResult(stages, 20_000, bytes_per_event, ratio, 0.4), 100.0, None)
    assert any("writer thread alone" in line for line in lines)
    assert any("replay source + decode + writer" in line for line in lines)


def test_device_drops_counts_only_losses() -> None:
    counters = {
        "ev0": {"delivered": 10, "packets_dropped": 2, "decoder_skipped_truncated": 0},
        "cam0": {"buffer_overflow": 1, "exposures": 5},
    }
    assert device_drops(counters) == {"ev0.packets_dropped": 2, "cam0.buffer_overflow": 1}
