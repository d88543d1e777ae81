"""Takes bounded by their trigger window: the per-device gate (synthetic packets, an injected
clock) and end to end on the sim rig (every written event inside the recorded window, what
fell outside counted; a slow sensor does not hold the stop beyond `writer.stop_backlog_s`)."""

from __future__ import annotations

import itertools
import json
import math
import time
import uuid
from collections.abc import Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import h5py
import numpy as np
import pytest
from pydantic import ValidationError

from rigd.app.capture import CaptureSession, run_capture
from rigd.app.capture.channel import DeviceChannel, TriggerChannel
from rigd.app.capture.gate import EventGate, FrameGate
from rigd.app.capture.stop import STOP_LEAD_S
from rigd.app.capture.window import TakeWindow
from rigd.app.config import default_sim_rig
from rigd.core.devices import PulseBatch
from rigd.core.events import EventArray, EventPacket, TriggerEvents
from rigd.core.frames import Frame
from rigd.core.settings import WriterConfig
from rigd.evt import Evt3Encoder, StreamDecoder
from rigd.take.reader import Take

RATE = 1000.0  # 1 ms period: round numbers
PERIOD = 1000


def _packet(t_events: Any, t_edges: Any = None, host_ns: int = 0) -> EventPacket:
    t_events = np.asarray(t_events, np.int64)
    n = t_events.size
    ev = EventArray.from_arrays(np.zeros(n), np.zeros(n), np.ones(n), t_events)
    edges = np.asarray([] if t_edges is None else t_edges, np.int64)
    trig = TriggerEvents(edges, np.ones(edges.size, np.uint8), np.zeros(edges.size, np.uint8))
    return EventPacket(ev, trig, host_ns)


def _events(parts: Sequence[object]) -> np.ndarray:
    return np.concatenate(
        [p.events.t for p in parts if isinstance(p, EventPacket)] or [np.empty(0, np.int64)]
    )


class Clock:
    def __init__(self) -> None:
        self.ns = 0

    def __call__(self) -> int:
        return self.ns


def test_events_before_the_first_edge_are_held_then_cut_at_the_margin() -> None:
    window = TakeWindow(RATE, margin_us=500, last_index=9)
    gate = EventGate("ev", "trigger_in", window)
    d0 = 100_000
    # Before pulse 0: held (the gate cannot place them yet).
    assert gate.admit(_packet(np.arange(d0 - 3000, d0 - 1000, 10))) == []
    assert gate.admit(_packet(np.arange(d0 - 1000, d0, 10))) == []
    out = gate.admit(_packet(np.arange(d0, d0 + 1000, 10), [d0]))
    kept = _events(out)
    assert kept.min() >= d0 - 500
    assert kept[0] == d0 - 500
    assert gate.counts.before == 250  # d0-3000 .. d0-510 every 10 us
    assert gate.counts.after == 0
    assert not gate.closed


def test_packets_are_split_at_the_window_end_and_the_gate_closes() -> None:
    window = TakeWindow(RATE, margin_us=0, last_index=4)  # end = pulse 4 + 1 period = d0 + 5000
    gate = EventGate("ev", "trigger_in", window)
    d0 = 7_000
    kept = []
    for k in range(8):
        lo = d0 + k * PERIOD
        out = gate.admit(_packet(np.arange(lo, lo + PERIOD, 100), [lo]))
        kept.append(_events(out))
        assert gate.closed is (lo + PERIOD - 100 >= d0 + 5 * PERIOD)
    t = np.concatenate(kept)
    assert t.min() == d0
    assert t.max() == d0 + 5 * PERIOD - 100
    assert gate.counts.after == 3 * 10
    assert gate.counts.triggers_after == 3
    assert gate.counts.before == 0


@pytest.mark.slow
def test_dropped_pulses_and_drift_keep_the_end_in_place() -> None:
    # 60 s at 30 Hz with a device clock 100 ppm fast: 6 ms of drift, a fifth of a period.
    rate, ppm = 30.0, 100.0
    window = TakeWindow(rate, margin_us=0, last_index=1799)
    gate = EventGate("ev", "trigger_in", window)
    d0 = 5_000_000
    k = np.arange(0, 1810)
    k = k[(k % 97 != 5) & ((k < 400) | (k > 460))]  # scattered drops and a 2 s gap
    rng = np.random.default_rng(1)
    d_edges = d0 + np.round(np.round(k * 1e6 / rate) * (1 + ppm * 1e-6) + rng.normal(0, 2, k.size))
    for edge in d_edges.astype(np.int64):
        gate.admit(_packet(np.array([edge, edge + 10]), np.array([edge])))
    true_end = d0 + round(1800 * 1e6 / rate) * (1 + ppm * 1e-6)
    assert gate.end_device_us is not None
    assert abs(gate.end_device_us - true_end) < 20
    kept_last = (k <= 1799).sum()
    assert gate.counts.after == 2 * (k.size - kept_last)
    assert gate.closed


def test_without_a_trigger_edge_the_window_falls_back_to_host_time() -> None:
    clock = Clock()
    window = TakeWindow(RATE, margin_us=0, last_index=9)
    window.note_pulses(np.array([0]), np.array([1_000_000]), np.array([10_000_000_000]))
    gate = EventGate("ev", "trigger_in", window, hold_s=1.0, clock_ns=clock)
    # Host ns of the window: [10.000 s, 10.010 s); the sensor's clock reads host us - 7 s.
    first = 2_000_000 + np.arange(10)
    assert gate.admit(_packet(first, host_ns=9_000_010_000)) == []
    clock.ns = 2_000_000_000  # past the hold: the held packet is placed by host time
    inside = 3_005_000 + np.arange(10)
    out = gate.admit(_packet(inside, host_ns=10_005_010_000))
    assert gate.mode == "host"
    assert gate.by_host_fallback
    assert _events(out).tolist() == inside.tolist()
    assert gate.counts.before == 10
    assert gate.admit(_packet(3_010_000 + np.arange(10), host_ns=10_010_010_000)) == []
    assert gate.counts.after == 10
    assert gate.closed


def test_host_mode_judges_a_late_packet_by_when_its_events_happened() -> None:
    """A backlog (a loaded host) delivers packets late: what the sensor made inside the window
    is kept though it is read after the window's end, and what it made before the window is
    outside though it is read inside it. Placed by the lower envelope of arrival - device time."""
    window = TakeWindow(RATE, margin_us=0, last_index=9)  # host ns [10.000 s, 10.010 s)
    window.note_pulses(np.array([0]), np.array([1_000_000]), np.array([10_000_000_000]))
    gate = EventGate("ev", "host", window)
    # On time: device us = host us - 7 s (+ 10 us of transport).
    assert gate.admit(_packet(2_990_000 + np.arange(10), host_ns=9_990_019_000)) == []
    assert gate.counts.before == 10
    # Made 5 ms before the window's start, read 3 ms inside it: outside.
    assert gate.admit(_packet(2_995_000 + np.arange(10), host_ns=10_003_000_000)) == []
    assert gate.counts.before == 20
    # Made at 10.008 s, read 50 ms after the window's end: kept, and the window is not closed
    # by the late arrival.
    late = 3_008_000 + np.arange(10)
    assert _events(gate.admit(_packet(late, host_ns=10_060_000_000))).tolist() == late.tolist()
    assert not gate.closed
    assert gate.counts.after == 0
    # Made after the window's end: outside, and the gate is closed.
    assert gate.admit(_packet(3_011_000 + np.arange(10), host_ns=10_070_000_000)) == []
    assert gate.counts.after == 10
    assert gate.closed


def test_a_sensor_clock_that_jumps_back_is_judged_by_arrival() -> None:
    """Device times far behind the arrival envelope (a clock reset) are no backlog: by arrival."""
    window = TakeWindow(RATE, margin_us=0, last_index=9)
    window.note_pulses(np.array([0]), np.array([1_000_000]), np.array([10_000_000_000]))
    gate = EventGate("ev", "host", window)
    hour = 3_600_000_000
    assert gate.admit(_packet(hour + 2_990_000 + np.arange(10), host_ns=9_990_010_000)) == []
    # The clock restarted near 0 (an hour behind): the packet is placed by its arrival, inside.
    reset = np.arange(100, 110)
    assert _events(gate.admit(_packet(reset, host_ns=10_004_000_000))).tolist() == reset.tolist()


def test_held_packets_are_placed_by_host_time_at_the_end() -> None:
    """A sensor whose trigger edges never came: what it held is placed by host time."""
    window = TakeWindow(RATE, margin_us=0, last_index=9)
    gate = EventGate("ev", "trigger_in", window, hold_s=60.0)
    assert gate.admit(_packet(2_000_000 + np.arange(10), host_ns=9_000_010_000)) == []
    inside = 3_005_000 + np.arange(10)
    assert gate.admit(_packet(inside, host_ns=10_005_010_000)) == []
    window.note_pulses(np.array([0]), np.array([1_000_000]), np.array([10_000_000_000]))
    kept = _events(gate.finish())
    assert kept.tolist() == inside.tolist()
    assert gate.counts.before == 10
    assert gate.by_host_fallback


def test_pulse_records_after_the_last_pulse_are_counted_not_kept() -> None:
    channel = SimpleNamespace(pulses_after_window=0)
    idx = np.arange(5, 10, dtype=np.int64)
    batch = PulseBatch(idx, idx * 1000, idx * 10)
    kept = TriggerChannel._clip(channel, batch, 7)  # type: ignore[arg-type]
    assert kept.index.tolist() == [5, 6, 7]
    assert channel.pulses_after_window == 2
    assert TriggerChannel._clip(channel, batch, None) is batch  # type: ignore[arg-type]


def test_frames_of_pulses_after_the_last_are_outside() -> None:
    window = TakeWindow(RATE, margin_us=0, last_index=2)
    gate = FrameGate("cam", "pulse_frames", window)
    image = np.zeros((2, 2), np.uint8)
    kept = []
    for k in (0, 1, 3, 4):  # frame of pulse 2 lost: the gate is not closed before pulse 3's
        kept += gate.admit(Frame(image, 40_000 + k * PERIOD + 3, 500, k, 0))
        assert gate.closed is (k >= 3)
    assert [f.frame_counter for f in kept if isinstance(f, Frame)] == [0, 1]
    assert gate.counts.after == 2


def test_host_mode_frames_against_the_pulse_records() -> None:
    window = TakeWindow(RATE, margin_us=1000, last_index=1)
    gate = FrameGate("cam", "host", window)
    image = np.zeros((2, 2), np.uint8)
    assert gate.admit(Frame(image, 0, 500, 0, 5_000_000)) == []  # no pulse record yet: held
    window.note_pulses(np.array([0, 1]), np.array([2_000, 3_000]), np.array([6_000_000, 7_000_000]))
    # Host window: [5.0 ms, 8.0 ms): the held frame (5.0 ms) is in.
    out = gate.admit(Frame(image, 1, 500, 1, 7_500_000))
    assert [f.frame_counter for f in out if isinstance(f, Frame)] == [0, 1]
    assert gate.admit(Frame(image, 2, 500, 2, 8_000_000)) == []
    assert gate.counts.after == 1
    assert gate.closed


def test_window_bounds_need_a_pulse_and_a_last_index() -> None:
    window = TakeWindow(30.0, margin_us=33_333)
    assert window.start_us is None
    assert window.end_us is None
    window.note_pulses(np.array([3]), np.array([1_100_000]), np.array([1]))  # pulse 0 lost
    assert window.first_pulse_us == 1_000_000
    assert window.start_us == 1_000_000 - 33_333
    window.set_last_index(149)
    assert window.end_us == 1_000_000 + round(149e6 / 30) + 33_333


def test_writer_config_validates_the_window_settings() -> None:
    assert WriterConfig().stop_backlog_s == 2.0
    assert WriterConfig().window_margin_us is None
    for bad in ({"stop_backlog_s": 0}, {"window_margin_us": -1}, {"window_hold_s": 0}):
        with pytest.raises(ValidationError):
            WriterConfig.model_validate(bad)


# -- end to end on the sim rig -------------------------------------------------------------------
def _sim_rig(tag: str, **writer: object) -> object:
    cfg = default_sim_rig(world=f"{tag}-{uuid.uuid4().hex[:8]}", resolution=(160, 90), pixel_format="mono8")
    data = cfg.model_dump(mode="json")
    data["writer"].update({"disk_reserve_mb": 0, "disk_ballast_mb": 24, **writer})
    return type(cfg).model_validate(data)


def _check_take_is_in_its_window(path: Path, tol_us: int) -> tuple[int, int, dict[str, dict[str, int]]]:
    with h5py.File(path) as f:
        start, end = int(f.attrs["window_start_us"]), int(f.attrs["window_end_us"])
        margin = int(f.attrs["window_margin_us"])
        outside = json.loads(f.attrs["window_outside_json"])
    with Take(path) as take:
        assert take.status == "complete"
        assert take.time_domain == "rig"
        pulses = take.pulses()
        first = int(pulses.t_us[np.argmin(pulses.index)])
        assert start == first - margin
        for sensor in take.event_sensors:
            t = take.sensor(sensor).events().t
            assert t.size > 0
            # The gate cuts in the sensor's clock; its rig times agree within the sync accuracy.
            assert t.min() >= start - tol_us, sensor
            assert t.max() < end + tol_us, sensor
            trig = take.sensor(sensor).triggers.t
            assert trig.size == 0 or (trig.min() >= start - tol_us and trig.max() < end + tol_us)
        for cam in take.cameras:
            ts = take.camera(cam).timestamps_us
            assert ts.size > 0, cam
            assert ts.min() >= start - tol_us, cam
            assert ts.max() < end + tol_us, cam
    assert set(outside) == {"trigger", "cam0", "cam1", "cam2", "ev0", "ev1"}
    return start, end, outside


@pytest.mark.slow
def test_sim_take_holds_its_trigger_window(tmp_path: Path) -> None:
    res = run_capture(_sim_rig("win"), tmp_path, 1.0)  # type: ignore[arg-type]
    start, end, outside = _check_take_is_in_its_window(res.path, tol_us=50)
    assert res.window_start_us == start
    assert res.window_end_us == end
    assert res.outside_window == outside
    period = round(1e6 / 30)
    assert end - start == round(29 * 1e6 / 30) + period + period  # 30 pulses, margin one period
    assert res.window_s == pytest.approx((end - start) / 1e6)
    # The sensors run on until they are stopped: what they sent past the end is counted.
    for sensor in ("ev0", "ev1"):
        assert outside[sensor]["after"] > 0
    assert not [r for r in res.report.losses if "take window" in r.reason]


@pytest.mark.slow
def test_slow_sensors_do_not_hold_the_stop(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Event packets reach the writer four times slower than the sensors make them: the stop
    waits `stop_backlog_s`, stops the sensors, reads for `stop_backlog_s` more and records
    what it did not get to, instead of draining a backlog that grows with the take."""
    deliver = DeviceChannel._deliver

    def slow(self: DeviceChannel, item: Frame | EventPacket) -> None:
        t = item.events.t if isinstance(item, EventPacket) else np.empty(0, np.int64)
        if t.size:  # a slow host: reading takes four times as long as the data lasted
            time.sleep(min(0.5, 4e-6 * (int(t[-1]) - int(t[0])) + 0.005))
        deliver(self, item)

    monkeypatch.setattr(DeviceChannel, "_deliver", slow)
    res = run_capture(_sim_rig("slow", stop_backlog_s=0.3), tmp_path, 1.5)  # type: ignore[arg-type]
    _check_take_is_in_its_window(res.path, tol_us=50)
    for sensor in ("ev0", "ev1"):
        reasons = [r.reason for r in res.report.losses if r.device == sensor]
        counters = res.report.device_counters[sensor]
        # What it did not get to is on record (the rest of its window too, when that was
        # still in its buffers; what its full buffers lost is in the device counters' record).
        # Whether a sensor still held data at the read deadline depends on how big its last
        # packets were (the host's pace): one that held none was read to its end.
        unread = counters["events_generated"] - counters["delivered"] - counters["device_dropped"]
        assert unread >= 0, counters
        assert unread == 0 or any("left unread" in r for r in reasons), (unread, reasons)


@pytest.mark.slow
def test_open_ended_take_ends_at_the_pulse_the_stop_fixed(tmp_path: Path) -> None:
    """A daemon's take (no duration) stopped by request: the window ends one period after the
    box's last pulse, at most STOP_LEAD_S of pulses past those seen when the stop came."""
    session = CaptureSession(_sim_rig("open"), tmp_path)  # type: ignore[arg-type]
    session.start()
    deadline = time.monotonic() + 60
    while session.progress().pulses < 10:
        assert time.monotonic() < deadline, "no pulses"
        assert session.wait(0.02) is None
    seen = session.progress().pulses
    session.request_stop("test stop")
    res = session.wait(120)
    assert res is not None
    _, end, _ = _check_take_is_in_its_window(res.path, tol_us=50)
    with Take(res.path) as take:
        pulses = take.pulses()
    b0 = int(pulses.t_us[np.argmin(pulses.index)])
    last = round((end - round(1e6 / 30) - b0) * 30 / 1e6)
    assert seen - 1 <= last <= seen - 1 + math.ceil(STOP_LEAD_S * 30) + 1  # records in flight
    assert last <= int(pulses.index.max())
    assert end == b0 + round(last * 1e6 / 30) + round(1e6 / 30)


def _word_packets(t_events: Any, t_edges: Any, cuts: Sequence[int], *, scan: bool) -> list[EventPacket]:
    """The events and edges as one EVT 3.0 stream cut into packets at event indices `cuts`, each
    carrying its words: scanned (events decoded only when asked) or decoded."""
    t = np.asarray(t_events, np.int64)
    x = (np.arange(t.size) * 7) % 1280
    ev = EventArray.from_arrays(x, np.full(t.size, 5), np.ones(t.size), t)
    edges = np.asarray(t_edges, np.int64)
    tr = TriggerEvents(edges, np.ones(edges.size, np.uint8), np.zeros(edges.size, np.uint8))
    enc, dec = Evt3Encoder(), StreamDecoder("evt3", width=1280, height=720)
    packets = []
    bounds = [0, *cuts, t.size]
    for a, b in itertools.pairwise(bounds):
        lo = t[a] if a < t.size else np.iinfo(np.int64).max
        hi = t[b] if b < t.size else np.iinfo(np.int64).max
        data = enc.encode(ev[a:b], tr[(tr.t >= (lo if a else -1)) & (tr.t < hi)])
        if scan:
            scanned, chunk = dec.scan_chunk(data)
            packets.append(scanned.packet(0, chunk))
        else:
            decoded, chunk = dec.feed_chunk(data)
            packets.append(EventPacket(decoded.events, decoded.triggers, 0, chunk))
    return packets


@pytest.mark.parametrize(
    ("parts", "before", "after", "kept"),
    [
        # held before the edge; across the start (the edge in it), inside, across the end, after
        (
            [(-3000, -1000, 50), (-500, 500, 50), (500, 4900, 100), (4900, 5500, 50), (6000, 7000, 50)],
            40,
            20,
            3,
        ),
        # a packet reaching past both ends with no event inside: its events are decoded to tell
        ([(-3000, -1000, 50), (-100, 6001, 6100), (6500, 7500, 50)], 41, 21, 0),
    ],
)
def test_packets_with_words_are_judged_by_their_span_as_by_their_events(
    parts: list[tuple[int, int, int]], before: int, after: int, kept: int
) -> None:
    """A sensor that only scans its words: the gate keeps whole packets with an event inside,
    and drops and counts the others, exactly as it does decoded ones."""
    d0 = 100_000
    ts = [np.arange(d0 + a, d0 + b, step) for a, b, step in parts]
    cuts = np.cumsum([len(t) for t in ts])[:-1].tolist()
    results = []
    for scan in (True, False):
        packets = _word_packets(np.concatenate(ts), [d0], cuts, scan=scan)
        assert all(p.from_scan is scan for p in packets[1:])  # the first: before a time base
        gate = EventGate("ev", "trigger_in", TakeWindow(RATE, margin_us=0, last_index=4))
        out = [part for p in packets for part in gate.admit(p)] + gate.finish()
        results.append(([(p.span, len(p.triggers)) for p in out if isinstance(p, EventPacket)], gate.counts))
    assert results[0] == results[1]
    spans, counts = results[0]
    assert (counts.before, counts.after) == (before, after)
    assert sum(1 for span, _ in spans if span.n) == kept
