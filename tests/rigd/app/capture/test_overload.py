"""Overload: event slices shed at the source with exact counts and time ranges, trigger edges
kept, the writer queue bounded in bytes, the writer's load measured on an injected clock."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
import pytest

from rigd.app.capture.faults import FaultBoard
from rigd.app.capture.items import EventsItem, FrameItem, WriterQueue
from rigd.app.capture.ledger import LossLedger
from rigd.app.capture.live import LiveStats
from rigd.app.capture.overload import SHED_REASON, SPAN_CLOSE_S, Fill, SliceShedder, WriterLoad
from rigd.app.capture.writer_loop import WriterLoop
from rigd.core.events import EventArray, EventPacket, TriggerEvents
from rigd.core.frames import Frame

CALM = Fill(0.1, 0.1)
FULL = Fill(0.9, 0.2)
HALF = Fill(0.6, 0.6)


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _packet(t0: int, n: int, *, host_ns: int = 0, triggers: int = 0) -> EventPacket:
    t = np.arange(t0, t0 + n, dtype=np.int64)
    events = EventArray(np.zeros(n, np.uint16), np.zeros(n, np.uint16), np.ones(n, np.int8), t)
    trig = TriggerEvents(
        np.arange(t0, t0 + triggers, dtype=np.int64),
        np.ones(triggers, np.uint8),
        np.zeros(triggers, np.uint8),
    )
    return EventPacket(events, trig, host_ns)


def _shedder(clock: Clock, **kw: float) -> tuple[SliceShedder, LossLedger, FaultBoard]:
    faults = FaultBoard()
    ledger = LossLedger(faults, dict)
    return SliceShedder("ev0", ledger, faults, clock=clock, **kw), ledger, faults


def test_a_shed_span_is_one_loss_record_with_its_exact_count_and_device_time_range() -> None:
    clock = Clock()
    shed, ledger, faults = _shedder(clock)
    assert shed.admit(_packet(0, 10), CALM, 0) is not None
    assert shed.admit(_packet(100, 10), FULL, 0) is None
    assert faults.is_active("overload", "ev0")
    # hysteresis: above `low` the gate keeps shedding though below `high`
    assert shed.admit(_packet(200, 5), HALF, 0) is None
    assert shed.admit(_packet(300, 7), CALM, 0) is not None
    assert ledger.records() == []  # the span stays open a moment: the next overload extends it
    clock.now += SPAN_CLOSE_S
    assert shed.admit(_packet(400, 1), CALM, 0) is not None
    [loss] = ledger.records()
    assert (loss.device, loss.what, loss.count, loss.t_first_us, loss.t_last_us) == (
        "ev0",
        "events",
        15,
        100,
        204,
    )
    assert loss.reason.startswith(SHED_REASON)
    assert not faults.is_active("overload", "ev0")
    assert shed.shed_events == 15


def test_trigger_edges_of_a_shed_packet_still_reach_the_writer() -> None:
    shed, _, _ = _shedder(Clock())
    kept = shed.admit(_packet(0, 50, triggers=2), FULL, 0)
    assert kept is not None
    assert len(kept.events) == 0
    assert kept.triggers.t.tolist() == [0, 1]
    assert kept.raw is None  # the wire bytes held the shed events: not stored


def test_a_packet_that_waited_too_long_is_shed_whatever_the_queue() -> None:
    shed, ledger, _ = _shedder(Clock(), max_lag_s=1.0)
    assert shed.admit(_packet(0, 3, host_ns=0), CALM, 999_000_000) is not None
    assert shed.admit(_packet(10, 3, host_ns=0), CALM, 1_001_000_000) is None
    shed.close()
    [loss] = ledger.records()
    assert loss.count == 3


def test_close_writes_the_open_span() -> None:
    shed, ledger, _ = _shedder(Clock())
    shed.admit(_packet(0, 4), FULL, 0)
    shed.close()
    assert [r.count for r in ledger.records()] == [4]
    shed.close()
    assert len(ledger.records()) == 1


@pytest.mark.parametrize(("low", "high"), [(0.5, 0.5), (0.0, 0.5), (0.5, 1.5)])
def test_bad_hysteresis_is_refused(low: float, high: float) -> None:
    faults = FaultBoard()
    with pytest.raises(ValueError, match="low"):
        SliceShedder("ev0", LossLedger(faults, dict), faults, low=low, high=high)


def test_the_queue_counts_bytes_and_a_put_over_the_byte_bound_is_a_counted_loss() -> None:
    faults = FaultBoard()
    ledger = LossLedger(faults, dict)
    q = WriterQueue(100, 0.01, ledger, faults, max_bytes=1000)
    live = LiveStats("rgb_camera")
    frame = Frame(np.zeros((20, 30), np.uint8), 5, 100, 0, 0)  # 600 bytes
    assert q.put(FrameItem("cam0", frame), live)
    assert q.bytes_queued == 600
    assert q.fill() == Fill(0.01, 0.6)
    assert q.put(FrameItem("cam0", frame), live)  # one item may overshoot the bound
    assert not q.put(FrameItem("cam0", frame), live)
    assert [r.count for r in ledger.records()] == [1]
    q.get(0.01)
    assert q.bytes_queued == 600
    q.get(0.01)
    assert q.bytes_queued == 0
    events = EventsItem("ev0", _packet(0, 10))
    assert events.nbytes == 130


def test_a_put_waiting_on_bytes_goes_on_once_the_writer_takes_an_item() -> None:
    faults = FaultBoard()
    q = WriterQueue(100, 30.0, LossLedger(faults, dict), faults, max_bytes=500)
    live = LiveStats("rgb_camera")
    frame = Frame(np.zeros((20, 30), np.uint8), 5, 100, 0, 0)
    assert q.put(FrameItem("cam0", frame), live)
    done = threading.Event()

    def put() -> None:
        assert q.put(FrameItem("cam0", frame), live)
        done.set()

    th = threading.Thread(target=put)
    th.start()
    q.get(1.0)  # frees the bytes: the waiting put proceeds
    th.join(30.0)
    assert done.is_set()
    assert q.bytes_queued == 600


def test_writer_load_is_the_busy_share_of_the_recent_window() -> None:
    clock = Clock()
    load = WriterLoad(clock)
    clock.now += 2.0
    load.add(clock.now - 0.5, clock.now)
    assert load.fraction() == pytest.approx(0.25)
    clock.now += 10.0
    assert load.fraction() == 0.0
    assert load.busy_s == pytest.approx(0.5)


def test_a_writer_behind_stores_words_uncompressed_until_it_caught_up() -> None:
    """Before any event slice is shed, the writer relieves itself of the compression: from
    `relieve_at` of the queue's bound until it is back under half of that."""
    fills = iter([0.02, 0.12, 0.5, 0.06, 0.049, 0.05, 0.1])
    calls: list[bool] = []
    queue = SimpleNamespace(fill=lambda: Fill(next(fills), 0.0))
    writer = SimpleNamespace(compress_events=calls.append)
    loop = WriterLoop(writer, queue, {}, None, None, None, None, 1.0, relieve_at=0.1)  # type: ignore[arg-type]
    for _ in range(7):
        loop._relieve()
    assert calls == [False, True, False]  # behind at 12 %, caught up at 4.9 %, behind again at 10 %
    assert loop.relieved == 2
