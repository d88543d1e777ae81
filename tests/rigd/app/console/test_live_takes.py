"""Latest-value publishing (bounded rate, nothing queued) and the take list's verdicts."""

from __future__ import annotations

import threading
import time
import uuid
from pathlib import Path

import h5py
import numpy as np
import pytest

from rigd.app.capture import run_capture
from rigd.app.config import RigConfig, default_sim_rig
from rigd.app.console.live import LatestSlot, LivePublisher, event_window
from rigd.app.console.takes import TakeList
from rigd.app.service.protocol import Telemetry
from rigd.core.events import EventArray
from rigd.core.frames import Frame


class FakeSource:
    """A daemon stand-in that counts how often it is sampled."""

    def __init__(self) -> None:
        self.samples = 0
        self.lock = threading.Lock()

    def telemetry(self) -> Telemetry:
        with self.lock:
            self.samples += 1
            seq = self.samples
        when = "2026-01-01T00:00:00Z"
        return Telemetry(seq=seq, time_utc=when, pid=1, state="capturing", bytes_written=seq)

    def latest_frames(self) -> dict[str, Frame]:
        return {}

    def latest_events(self) -> dict[str, tuple[EventArray, tuple[int, int]]]:
        t = np.arange(0, 100_000, 1000, dtype=np.int64)
        n = t.size
        ev = EventArray(np.full(n, 3, np.uint16), np.full(n, 2, np.uint16), np.ones(n, np.int8), t)
        return {"ev0": (ev, (16, 8))}


def test_latest_slot_keeps_only_the_newest() -> None:
    slot: LatestSlot[int] = LatestSlot()
    assert slot.get() == (0, None)
    for i in range(100):
        slot.put(i)
    assert slot.get() == (100, 99)


@pytest.mark.slow
def test_many_readers_cost_one_sample_per_period() -> None:
    """Fifty threads asking for the status as fast as they can: the daemon is sampled at most
    once per publication period (5 Hz), whoever asks."""
    source = FakeSource()
    live = LivePublisher(source, rate_hz=5.0, thumbnail_width=16)
    stop = threading.Event()

    def reader() -> None:
        while not stop.is_set():
            assert live.fresh_status()["state"] == "capturing"

    threads = [threading.Thread(target=reader) for _ in range(50)]
    t0 = time.monotonic()
    for t in threads:
        t.start()
    stop.wait(1.0)
    stop.set()
    for t in threads:
        t.join()
    elapsed = time.monotonic() - t0
    assert 1 <= source.samples <= 5 * elapsed + 2
    assert live.state.preview_versions()["ev0"] == source.samples  # one preview per sample, shared


def test_publisher_sleeps_while_nobody_watches() -> None:
    source = FakeSource()
    live = LivePublisher(source, rate_hz=20.0, thumbnail_width=16)
    live.start()
    try:
        deadline = time.monotonic() + 10
        while live.idle_waits < 3:  # three idle turns of its loop
            assert time.monotonic() < deadline, "the publisher thread did not run"
            time.sleep(0.02)
        assert source.samples == 0
        live.want()
        deadline = time.monotonic() + 10
        while source.samples < 3:
            assert time.monotonic() < deadline, "the publisher did not start publishing"
            time.sleep(0.02)
    finally:
        live.close()


def test_event_window_keeps_the_last_milliseconds() -> None:
    t = np.arange(0, 100_000, 1000, dtype=np.int64)
    n = t.size
    ev = EventArray(np.zeros(n, np.uint16), np.zeros(n, np.uint16), np.ones(n, np.int8), t)
    w = event_window(ev, 10)
    assert int(w.t.min()) == 89_000
    assert len(w) == 11
    assert len(event_window(ev[np.arange(0)], 10)) == 0


@pytest.fixture(scope="module")
def take(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("takes")
    cfg = default_sim_rig(world=f"tl-{uuid.uuid4().hex[:6]}", resolution=(64, 48), clock="virtual")
    data = cfg.model_dump(mode="json")
    data["writer"]["disk_reserve_mb"] = 0
    data["writer"]["disk_ballast_mb"] = 24
    return run_capture(RigConfig.from_data(data), out, 0.5).path


@pytest.mark.slow
def test_take_list_says_what_a_take_needs(take: Path) -> None:
    takes = TakeList(take.parent, thumbnail_width=32)
    (entry,) = takes.entries()
    assert entry.status == "complete"
    assert entry.action is None
    assert sum(entry.frames.values()) > 0
    assert takes.preview(take.name, "cam0")[:2] == b"\xff\xd8"  # a JPEG
    rates = takes.event_rates(take.name)
    assert set(rates) == {"ev0", "ev1"}
    assert len(rates["ev0"]["rate_hz"]) > 0
    # The same take left unfinished (as a killed writer leaves it): run rigd recover.
    unfinished = take.with_name("unfinished.h5")
    unfinished.write_bytes(take.read_bytes())
    with h5py.File(unfinished, "r+") as f:
        f.attrs["status"] = "recording"
    (take.parent / "garbage.h5").write_bytes(b"not a take")
    by_name = {e.name: e for e in takes.entries()}
    assert by_name["unfinished.h5"].action is not None
    assert f"rigd recover {unfinished}" in by_name["unfinished.h5"].action
    assert by_name["garbage.h5"].status == "unreadable"
    assert "rigd recover" in (by_name["garbage.h5"].action or "")
    assert by_name[take.name].status == "complete"
    with pytest.raises(Exception, match="not a take name"):
        takes.path_of("../etc/passwd")


def test_write_rate_spans_flushes() -> None:
    """The take file grows once a second (at each flush); the rate shown must not drop to zero
    between flushes."""
    now = [0.0]
    live = LivePublisher(FakeSource(), rate_hz=5.0, clock=lambda: now[0])
    rates = []
    for i in range(40):  # 8 s at 5 Hz, 1 MB flushed every second
        now[0] = i * 0.2
        rates.append(live._write_rate(now[0], (i // 5) * 1_000_000))
    assert min(rates[10:]) > 0.5e6
    assert max(rates[10:]) < 1.6e6
