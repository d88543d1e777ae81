"""The capture parts on their own: queue losses, the fault board, the ledger's journal, the
disk and flush watchdogs, the pulse log and the per-device drain rule."""

from __future__ import annotations

from collections import namedtuple
from pathlib import Path

import numpy as np
import pytest

from rigd.app.capture.channel import DeviceChannel, pulse_log
from rigd.app.capture.control import RunControl
from rigd.app.capture.faults import DiskWatch, FaultBoard, FlushWatch
from rigd.app.capture.items import EventsItem, FrameItem, Stop, WriterQueue
from rigd.app.capture.ledger import LossLedger
from rigd.app.capture.live import LiveStats, Observations
from rigd.app.capture.streams import CameraStream, EventStream
from rigd.core.devices import PulseBatch
from rigd.core.errors import TakeError
from rigd.core.events import EventArray, EventPacket, TriggerEvents
from rigd.core.frames import Frame

Usage = namedtuple("Usage", "total used free")


def _frame(t: int) -> Frame:
    return Frame(np.zeros((2, 2), np.uint8), t, 100, 0, 0)


def _packet(ts: list[int]) -> EventPacket:
    n = len(ts)
    events = EventArray(
        np.zeros(n, np.uint16), np.zeros(n, np.uint16), np.ones(n, np.int8), np.asarray(ts, np.int64)
    )
    return EventPacket(events, TriggerEvents.empty(), 0)


def test_full_queue_is_a_counted_loss_with_its_time_range_and_a_fault_that_clears() -> None:
    faults = FaultBoard()
    ledger = LossLedger(faults, dict)
    q = WriterQueue(4, 0.001, ledger, faults)
    live = LiveStats("rgb_camera")
    assert all(q.put(FrameItem("cam0", _frame(t)), live) for t in range(4))
    assert not q.put(FrameItem("cam0", _frame(99)), live)
    [loss] = ledger.records()
    assert (loss.device, loss.what, loss.count, loss.t_first_us, loss.t_last_us) == (
        "cam0",
        "frames",
        1,
        99,
        99,
    )
    assert live.queued == 4  # the refused item is not counted as queued
    assert faults.is_active("queue_full", None)
    for _ in range(4):
        q.get(0.01)
    assert q.put(EventsItem("ev0", _packet([5, 7])), LiveStats("event_sensor"))
    assert not faults.is_active("queue_full", None)  # the writer caught up
    assert any(line.startswith("fault queue_full") for line in faults.history())


def test_stop_item_and_empty_queue() -> None:
    faults = FaultBoard()
    q = WriterQueue(2, 0.01, LossLedger(faults, dict), faults)
    assert q.get(0.0) is None
    q.put_stop()
    assert q.get(0.1) is Stop.STOP


def test_ledger_journal_holds_losses_write_offs_counters_and_faults() -> None:
    faults = FaultBoard()
    ledger = LossLedger(faults, lambda: {"corrupt_lines": 3})
    ledger.add("ev0", "events", 12, "decoder skipped", (10, 20))
    ledger.write_off("cam1", "frames", "unplugged", 1234)
    ledger.set_counters("ev0", {"delivered": 5})
    faults.set("disk_low", None, "low")
    faults.note("cam1 re-tied")
    journal = ledger.journal()
    assert [r["count"] for r in journal["losses"]] == [12, 0]
    assert journal["losses"][1]["t_first_us"] == 1234
    assert journal["failed_devices"] == {"cam1": "unplugged"}
    assert journal["device_counters"] == {"ev0": {"delivered": 5}}
    assert journal["faults"][0].startswith("fault disk_low from ")
    assert journal["fault_history"] == ["cam1 re-tied"]
    assert journal["trigger_link"] == {"corrupt_lines": 3}
    assert ledger.lost_by_device() == {"ev0": 12, "cam1": 0}
    assert ledger.is_written_off("cam1")
    assert not ledger.is_written_off("ev0")


def test_disk_watch_refuses_a_take_below_the_reserve_and_stops_a_running_one(tmp_path: Path) -> None:
    faults, control = FaultBoard(), RunControl()
    free = {"mb": 500}
    watch = DiskWatch(tmp_path, 1000, faults, control, lambda _p: Usage(0, 0, free["mb"] * 1_000_000))
    with pytest.raises(TakeError, match="not starting a take: 500 MB free"):
        watch.check(preflight=True)
    assert not control.stop_requested.is_set()
    watch.check()
    assert control.stop_requested.is_set()
    assert control.stop_by_fault
    assert faults.is_active("disk_low", None)
    free["mb"] = 2000
    watch.check()
    assert not faults.is_active("disk_low", None)


def test_flush_watch_says_when_flushes_stop_and_clears_when_they_resume() -> None:
    faults = FaultBoard()
    watch = FlushWatch(1.0, faults)
    watch.check(now=10.0, since=8.0)
    assert not faults.is_active("writer_stalled", None)
    watch.check(now=10.0, since=6.9)  # over max(3 intervals, interval + 2 s)
    assert faults.is_active("writer_stalled", None)
    watch.check(now=11.0, since=10.5)
    assert not faults.is_active("writer_stalled", None)


def test_pulse_log_keeps_one_record_per_index() -> None:
    a = PulseBatch(np.array([0, 1, 2]), np.array([0, 100, 200]), np.array([5, 6, 7]))
    b = PulseBatch(np.array([2, 3]), np.array([200, 300]), np.array([7, 8]))  # re-read after a gap
    log = pulse_log([a, b], emitted=6)
    assert log.index.tolist() == [0, 1, 2, 3]
    assert log.t_us.tolist() == [0, 100, 200, 300]
    assert log.n_emitted == 6
    assert pulse_log([], emitted=0).index.size == 0


def test_observations_interval_jitter() -> None:
    obs = Observations()
    assert obs.interval_jitter_us(1000.0) is None
    obs.t.extend([0, 1000, 2000, 4000, 5000])  # one missed pulse is a whole period, no jitter
    assert obs.interval_jitter_us(1000.0) == pytest.approx(0.0)


@pytest.mark.parametrize(
    ("kind", "newest", "expected"),
    [
        ("rgb_camera", None, False),
        ("rgb_camera", 1_000, True),  # the frame exposed on the last pulse is in
        ("event_sensor", 1_000, False),
        ("event_sensor", 1_000 + 2 * 33_333_333, True),  # data two periods past the last pulse
    ],
)
def test_drain_rule_per_device(kind: str, newest: int | None, expected: bool) -> None:
    ch = DeviceChannel.__new__(DeviceChannel)  # the rule reads only its stream and live counters
    ch.live = LiveStats(kind)  # type: ignore[arg-type]
    ch.stream = CameraStream("dev", ch.live) if kind == "rgb_camera" else EventStream("dev", ch.live)
    ch.live.last_host_ns = newest
    assert ch.drained(1_000, 33_333_333) is expected
    ch.live.state = "reconnecting"
    assert ch.drained(1_000, 33_333_333)  # a device away is not waited for
