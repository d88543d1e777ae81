"""A follower host's trigger: the coordinator's records, in order, none taken twice or lost."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from rigd.app.capture import remote_trigger
from rigd.app.capture.remote_trigger import FeedState, RemoteTrigger
from rigd.core.errors import DeviceError
from rigd.core.host_clock import MONOTONIC, HostClock
from rigd.core.settings import TriggerSettings

PERIOD_US = 33_333


class FakeCoordinator:
    """The coordinator's `pulses` answers, from a box whose records the test emits."""

    name = "host A (test)"

    def __init__(self, per_reply: int = 3) -> None:
        self.t_us: list[int] = []
        self.emitted: int | None = None
        self.per_reply = per_reply
        self.fail = 0
        self.calls = 0
        self.lock = threading.Lock()
        self.answer_from: int | None = None
        self.skew_ns = 5_000_000_000
        self.clock: HostClock = MONOTONIC
        """The clock this host reads (the coordinator's runs `skew_ns` ahead of it)."""

    def emit(self, n: int) -> None:
        with self.lock:
            k = len(self.t_us)
            self.t_us += [1_000 + (k + i) * PERIOD_US for i in range(n)]

    def stop(self) -> None:
        with self.lock:
            self.emitted = len(self.t_us)

    def fetch(self, since: int) -> FeedState:
        with self.lock:
            self.calls += 1
            if self.fail:
                self.fail -= 1
                raise DeviceError("no reply within 5 s")
            start = since if self.answer_from is None else self.answer_from
            t = self.t_us[start : start + self.per_reply]
            index = np.arange(start, start + len(t), dtype=np.int64)
            clock = self.t_us[-1] if self.t_us else 0
            # The coordinator's monotonic clock runs 5 s ahead of this one; each record reached
            # it 2 ms after its box time.
            host = np.asarray(t, np.int64) * 1000 + 2_000_000 + self.skew_ns
            now = self.clock.now_ns() + self.skew_ns
            return FeedState(
                index, np.asarray(t, np.int64), self.emitted is None, self.emitted, clock, host, now
            )


def opened(feed: FakeCoordinator) -> RemoteTrigger:
    trig = RemoteTrigger(feed, spec="rigd-host://A/take")
    trig.configure(TriggerSettings(rate_hz=30.0, pulse_width_us=1000))
    trig.arm()
    trig.start(10)
    return trig


def read_all(trig: RemoteTrigger, n: int) -> tuple[list[int], list[int]]:
    index: list[int] = []
    t_us: list[int] = []
    for _ in range(100):
        if len(index) >= n:
            break
        b = trig.read_pulses(0.01)
        index += b.index.tolist()
        t_us += b.t_us.tolist()
    return index, t_us


def test_records_arrive_in_order_across_replies_and_stop_returns_the_box_count() -> None:
    feed = FakeCoordinator(per_reply=3)
    trig = opened(feed)
    assert trig.follows
    assert trig.is_running()
    feed.emit(10)
    index, t_us = read_all(trig, 10)
    assert index == list(range(10))
    assert t_us == feed.t_us
    feed.stop()
    assert trig.stop() == 10
    assert not trig.is_running()
    assert len(trig.read_pulses(0.0)) == 0
    assert trig.link_stats()["records"] == 10


def test_arrival_times_come_on_this_hosts_clock() -> None:
    """The coordinator's arrival times, moved onto this host's monotonic clock by the offset
    its answers imply (a coordinator clock 5 s ahead here): within the round trip."""
    feed = FakeCoordinator(per_reply=100)
    trig = opened(feed)
    feed.emit(3)
    b = trig.read_pulses(0.5)
    expected = b.t_us * 1000 + 2_000_000  # the arrival on the coordinator, without its skew
    rtt_ns = trig.link_stats()["clock_rtt_us"] * 1000
    assert np.all(np.abs(b.host_time_ns - expected) <= rtt_ns // 2 + 1000)


class StandingClock:
    """A virtual world's host clock while its time stands still: far from the monotonic one."""

    def now_ns(self) -> int:
        return 10**12


def test_arrival_times_come_on_the_host_clock_of_this_hosts_devices() -> None:
    """On a virtual world the session hands the remote trigger its devices' clock: the offset
    is measured on it (both sides read their world's clock), so the records land on it exactly
    when time stands still during the round trip."""
    feed = FakeCoordinator(per_reply=100)
    feed.clock = StandingClock()
    trig = opened(feed)
    assert trig.host_clock is MONOTONIC
    trig.use_host_clock(feed.clock)
    assert trig.host_clock is feed.clock
    feed.emit(3)
    b = trig.read_pulses(0.5)
    assert b.host_time_ns.tolist() == (b.t_us * 1000 + 2_000_000).tolist()
    assert trig.link_stats()["clock_rtt_us"] == 0


def test_a_reply_without_a_clock_reading_is_taken_and_sets_no_offset() -> None:
    """A coordinator whose trigger is not open yet has no host clock to read: `now_ns` None."""
    from rigd.app.service.host_links import CoordinatorFeed, feed_reply

    empty = np.empty(0, np.int64)
    reply = feed_reply(FeedState(empty, empty, True, None, 0, empty, None), 100)

    class Link:
        name = "host A (test)"

        def call(self, cmd: str, **args: object) -> dict[str, object]:
            return reply

    state = CoordinatorFeed(Link(), "take").fetch(0)  # type: ignore[arg-type]
    assert state.now_ns is None
    assert len(state.index) == 0


def test_probes_and_stop_look_without_taking_records() -> None:
    feed = FakeCoordinator(per_reply=100)
    trig = opened(feed)
    feed.emit(5)
    assert trig.pulse_count() == 0  # the box still runs: what this host has taken so far
    assert trig.clock_us() == feed.t_us[-1]
    index, _ = read_all(trig, 5)
    assert index == list(range(5))  # the probes took none of them


def test_a_reply_out_of_order_is_an_error_naming_the_coordinator() -> None:
    feed = FakeCoordinator()
    trig = opened(feed)
    feed.emit(6)
    read_all(trig, 3)
    feed.answer_from = 5  # skips 3 and 4
    with pytest.raises(DeviceError, match=r"host A .*records from 5 answered a request from 3"):
        trig.read_pulses(0.0)


def test_a_failing_feed_is_counted_then_lost(monkeypatch: pytest.MonkeyPatch) -> None:
    feed = FakeCoordinator()
    trig = opened(feed)
    feed.emit(2)
    feed.fail = 2
    assert len(trig.read_pulses(0.0)) == 0  # one failure: not lost yet
    assert trig.link_stats()["feed_errors"] == 1
    assert trig.link_lost() is None
    monkeypatch.setattr(remote_trigger, "FEED_LOST_S", -1.0)
    assert len(trig.read_pulses(0.0)) == 0
    lost = trig.link_lost()
    assert lost is not None
    assert "host A (test) has not answered" in lost
    assert "no reply" in lost
    assert read_all(trig, 2)[0] == [0, 1]  # records that come after all: nothing was skipped
    assert trig.stop() == 2  # lost: no wait for the box's count


def test_stop_keeps_what_was_fetched_when_the_coordinator_never_says(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(remote_trigger, "STOP_WAIT_S", 0.0)
    feed = FakeCoordinator()
    trig = opened(feed)
    feed.emit(4)
    read_all(trig, 4)
    assert trig.stop() == 4  # the box never stopped: the records this host holds
