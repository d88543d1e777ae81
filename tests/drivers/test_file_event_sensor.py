"""`file://` replay of real RAW/DAT recordings through the production decoder, and the
event-sensor lifecycle contract on synthetic recordings (a replay takes no live pulses, so
the trigger-in contract is not its to run)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from drivers.base import Capability, EventSensor
from drivers.evt_file_stream import Pace
from drivers.file_event_sensor import FileEventSensor
from drivers.registry import open_device
from drivers.testing.event_sensor import EventSensorLifecycleContract
from rigd.core.errors import ConfigError, DeviceError
from rigd.core.events import EventArray, EventPacket, TriggerEvents
from rigd.core.settings import EventSensorSettings
from rigd.evt import RawHeader, StreamDecoder, parse_raw_header, read_raw, write_dat, write_raw

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "events"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"shared test data not found at {DATA}")


def _recording(tmp_path: Path, fmt: str, *, with_triggers: bool = False) -> Path:
    """5000 events over 50 ms (and two trigger pulses when asked) as a RAW or DAT file."""
    t = np.arange(5000, dtype=np.int64) * 10 + 1_000
    ev = EventArray.from_arrays(t % 320, (t // 320) % 240, np.where(t % 20 == 0, 1, -1), t)
    if fmt == "dat":
        path = tmp_path / "rec.dat"
        write_dat(path, ev, width=320, height=240)
        return path
    trig = None
    if with_triggers:
        trig = TriggerEvents(
            np.array([2_000, 2_200, 12_000, 12_200], np.int64),
            np.array([1, 0, 1, 0], np.uint8),
            np.zeros(4, np.uint8),
        )
    path = tmp_path / f"rec-{fmt}.raw"
    write_raw(path, RawHeader(fmt=fmt, width=320, height=240), ev, trig)
    return path


class TestFileReplayContract(EventSensorLifecycleContract):
    @pytest.fixture(params=["evt3", "evt2", "evt21", "dat"])
    def sensor(self, request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[EventSensor]:
        sensor = open_device("event_sensor", f"file://{_recording(tmp_path, request.param)}?chunk_bytes=4096")
        yield sensor
        sensor.close()


@pytest.mark.parametrize("fmt", ["evt3", "evt2", "dat"])
def test_trigger_in_only_when_the_recording_holds_trigger_edges(tmp_path: Path, fmt: str) -> None:
    plain = open_device("event_sensor", f"file://{_recording(tmp_path, fmt)}")
    assert plain.capabilities == {Capability.DEVICE_TIMESTAMPS}
    with pytest.raises(ConfigError, match="trigger_in"):
        plain.configure(EventSensorSettings(enable_trigger_in=True))
    if fmt == "dat":
        return  # DAT files hold change events only
    wired = open_device("event_sensor", f"file://{_recording(tmp_path, fmt, with_triggers=True)}")
    assert Capability.TRIGGER_IN in wired.capabilities
    wired.configure(EventSensorSettings(enable_trigger_in=True))
    wired.start()
    packets = _drain(wired, 0.0)
    assert len(TriggerEvents.concatenate([p.triggers for p in packets]).rising(0)) == 2


def _drain(sensor: object, timeout: float = 0.2) -> list[EventPacket]:
    out = []
    while (p := sensor.read_events(timeout)) is not None:  # type: ignore[attr-defined]
        out.append(p)
    return out


@needs_data
@pytest.mark.parametrize(
    ("name", "count", "first", "last"),
    [
        ("evt3_gen41_sample.raw", 219_596, 11_718_656, 11_727_457),
        ("evt2_gen3_sample.raw", 539_481, 1_317_888, 1_367_888),
        ("evt3_pedestrians.raw", 5_000, 5_840_504, 5_885_714),
    ],
)
def test_fast_replay_gives_every_event(name: str, count: int, first: int, last: int) -> None:
    sensor = open_device("event_sensor", f"file://{DATA / name}?chunk_bytes=4093")
    sensor.start()
    packets = _drain(sensor, 0.0)
    sensor.stop()
    ev = EventArray.concatenate([p.events for p in packets])
    assert len(ev) == count
    assert (int(ev.t[0]), int(ev.t[-1])) == (first, last)
    assert sensor.stats().delivered == count
    w, h = sensor.geometry
    assert int(ev.x.max()) < w
    assert int(ev.y.max()) < h


@needs_data
def test_dat_replay() -> None:
    sensor = open_device("event_sensor", f"file://{DATA / 'dat_ncars_sample.dat'}")
    sensor.start()
    ev = EventArray.concatenate([p.events for p in _drain(sensor, 0.0)])
    assert len(ev) == 4_407


def test_paced_replay_releases_events_no_earlier_than_their_time(tmp_path: Path) -> None:
    # 200 ms of synthetic events, replayed in real time.
    t = np.arange(0, 200_000, 50, dtype=np.int64) + 1_000
    ev = EventArray.from_arrays(t % 640, (t // 640) % 480, np.where(t % 100 == 0, 1, 0), t)
    path = tmp_path / "rec.raw"
    write_raw(path, RawHeader(fmt="evt3", width=640, height=480), ev)
    clock = FakeClock()  # host time moves when the sensor sleeps: the test never waits on it
    sensor = FileEventSensor(path, pace=1, clock=clock, sleep=clock.sleep)
    start = clock.now
    sensor.start()
    seen = 0
    while (p := sensor.read_events(0.5)) is not None:
        elapsed_us = (clock.now - start) * 1e6
        # Nothing may be released before its time has come on the host clock.
        assert int(p.events.t[-1]) - int(t[0]) <= elapsed_us + 1_000
        seen += len(p.events)
    assert seen == len(ev)
    assert clock.now - start >= 0.19


@pytest.mark.slow
def test_loop_keeps_time_increasing(tmp_path: Path) -> None:
    t = np.arange(100, 10_100, 100, dtype=np.int64)
    ev = EventArray.from_arrays(np.zeros_like(t), np.zeros_like(t), np.ones_like(t), t)
    trig = TriggerEvents(np.array([150], np.int64), np.array([1], np.uint8), np.array([0], np.uint8))
    path = tmp_path / "loop.raw"
    write_raw(path, RawHeader(fmt="evt3", width=64, height=64), ev, trig)
    sensor = open_device("event_sensor", f"file://{path}?loop=1")
    sensor.start()
    packets = [sensor.read_events(0.1) for _ in range(40)]
    sensor.stop()
    all_t = np.concatenate([p.events.t for p in packets if p is not None])
    assert len(all_t) > 3 * len(t)
    assert (np.diff(all_t) > 0).all()
    trig_t = np.concatenate([p.triggers.t for p in packets if p is not None])
    assert (np.diff(trig_t) > 0).all()
    assert len(trig_t) >= 3
    assert sensor.stats().extra["passes"] >= 4


@needs_data
def test_same_events_as_whole_file_decode() -> None:
    path = DATA / "evt3_gen41_sample.raw"
    _, whole = read_raw(path)
    sensor = open_device("event_sensor", f"file://{path}?chunk_bytes=777")
    sensor.start()
    ev = EventArray.concatenate([p.events for p in _drain(sensor, 0.0)])
    for col in ("x", "y", "p", "t"):
        np.testing.assert_array_equal(getattr(ev, col), getattr(whole.events, col))


@needs_data
def test_errors_name_the_problem(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        open_device("event_sensor", f"file://{tmp_path / 'nope.raw'}")
    with pytest.raises(ConfigError, match="unknown parameter"):
        open_device("event_sensor", f"file://{DATA / 'evt3_pedestrians.raw'}?speed=2")
    sensor = open_device("event_sensor", f"file://{DATA / 'evt3_pedestrians.raw'}")
    sensor.start()
    with pytest.raises(DeviceError, match="configure while started"):
        sensor.configure(EventSensorSettings())
    sensor.close()
    with pytest.raises(DeviceError, match="closed"):
        sensor.read_events(0.0)


@pytest.mark.parametrize(
    ("make", "problem"),
    [
        (lambda d: d, "is a directory"),
        (lambda d: _write(d / "z.raw", b""), "empty file"),
        (
            lambda d: _write(d / "w.raw", b"% format EVT3;width=abc;height=720\n% end\n"),
            "'abc' is not an integer",
        ),
        (lambda d: _write(d / "g.raw", b"% geometry 640xabc\n% end\n"), "'abc' is not an integer"),
        (lambda d: _write(d / "b.raw", b"% format EVT3;width=9000;height=720\n% end\n"), "outside 1..2048"),
        (
            lambda d: _write(d / "r.raw", bytes(np.random.default_rng(0).integers(0, 256, 999, np.uint8))),
            "no RAW header",
        ),
        (
            lambda d: _write(d / "h.dat", b"% Width abc\n% Height 4\n\x0c\x08"),
            "Width 'abc' is not an integer",
        ),
        (lambda d: _write(d / "k.dat", b"% Width 4\n"), "ends before the event type"),
    ],
)
def test_unreadable_files_are_one_line_config_errors(
    tmp_path: Path, make: Callable[[Path], Path], problem: str
) -> None:
    """A directory, an empty file, bad header numbers, random bytes, a bad DAT header: one line
    naming the file and the problem."""
    path = make(tmp_path)
    with pytest.raises(ConfigError, match=problem) as exc:
        open_device("event_sensor", f"file://{path}")
    assert str(path) in str(exc.value)
    assert "\n" not in str(exc.value)


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def test_a_corrupt_word_costs_only_its_events_in_replay(tmp_path: Path) -> None:
    path = _recording(tmp_path, "evt3")
    ref = EventArray.concatenate([p.events for p in _drain(open_started(path), 0.0)])
    data = bytearray(path.read_bytes())
    hdr_size = data.index(b"% end\n") + 6
    words = np.frombuffer(bytes(data[hdr_size:]), "<u2")
    tl = np.flatnonzero((words >> 12) == 6)
    i = int(tl[len(tl) // 2])
    data[hdr_size + 2 * i : hdr_size + 2 * i + 2] = (0x6000).to_bytes(2, "little")
    bad = tmp_path / "bad.raw"
    bad.write_bytes(bytes(data))
    sensor = open_started(bad)
    ev = EventArray.concatenate([p.events for p in _drain(sensor, 0.0)])
    extra = sensor.stats().extra
    assert ev.is_time_sorted()
    assert len(ev) + extra["decoder_skipped_non_monotonic_time"] == len(ref)
    assert extra["decoder_skipped_non_monotonic_time"] > 0
    assert extra["decoder_first_skipped_offset"] >= hdr_size + 2 * i


def open_started(path: Path) -> EventSensor:
    sensor = open_device("event_sensor", f"file://{path}?chunk_bytes=501")
    sensor.start()
    return sensor


# ---------------------------------------------------------------- wire-byte replay (EVT 3.0 / 2.0)
class FakeClock:
    """Host time that moves only when the sensor sleeps (or the test says so)."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now

    def sleep(self, s: float) -> None:
        self.now += max(s, 1e-6)


def _rechunked(packets: list[EventPacket], fmt: str, geometry: tuple[int, int]) -> EventArray:
    """Each packet's EvtChunk decoded alone from its state: must give the packet's events, and
    the chunks must follow each other without a gap."""
    prev = None
    for p in packets:
        assert p.raw is not None
        assert p.raw.fmt == fmt
        assert prev is None or p.raw.continues(prev)
        dec = StreamDecoder(fmt, width=geometry[0], height=geometry[1])
        dec._state[:] = p.raw.state  # TODO: StreamDecoder's own state setter once it lands
        got = dec.feed(p.raw.data)
        assert dec.bytes_consumed == len(p.raw.data)
        for col in ("x", "y", "p", "t"):
            np.testing.assert_array_equal(getattr(got.events, col), getattr(p.events, col))
        np.testing.assert_array_equal(got.triggers.t, p.triggers.t)
        prev = p.raw
    return EventArray.concatenate([p.events for p in packets])


@needs_data
@pytest.mark.parametrize("pace", [0.5, 2.0])
def test_paced_wire_replay_never_hands_out_bytes_ahead_of_time(pace: float) -> None:
    path = DATA / "evt3_gen41_sample.raw"
    clock = FakeClock()
    sensor = FileEventSensor(path, pace=pace, clock=clock, sleep=clock.sleep, packet_us=250)
    assert sensor.wire
    sensor.start()
    t_start = clock.now
    first_t = 11_718_656  # the recording's first TIME_HIGH (its first period starts there)
    packets = []
    while (p := sensor.read_events(0.01)) is not None:
        due_us = (clock.now - t_start) * 1e6 * pace
        assert int(p.events.t[-1]) - first_t <= due_us
        # stamped when its bytes were due (in memory), not when it was read
        arrived_s = p.host_time_ns / 1e9
        assert arrived_s <= clock.now + 1e-9
        assert int(p.events.t[-1]) - first_t <= (arrived_s - t_start) * 1e6 * pace + 1
        packets.append(p)
        clock.now += 0.0003  # the reader's own time between reads
    ev = _rechunked(packets, "evt3", sensor.geometry)
    _, whole = read_raw(path)
    assert len(ev) == len(whole.events) == sensor.stats().delivered
    np.testing.assert_array_equal(ev.t, whole.events.t)
    assert len(packets) > 10  # paced: many buffers, not one
    with path.open("rb") as f:
        header = parse_raw_header(f).size
    assert sensor.stats().extra["bytes_delivered"] == path.stat().st_size - header


@needs_data
def test_looped_gen41_stream_repeats_whole_periods_gap_free() -> None:
    path = DATA / "evt3_gen41_sample.raw"
    _, whole = read_raw(path)
    t0 = int(whole.events.t[0])
    per_pass = int(np.count_nonzero(whole.events.t < t0 + 8192))
    sensor = FileEventSensor(path, loop=True, chunk_bytes=100_003)
    sensor.start()
    packets = [sensor.read_events(0.0) for _ in range(40)]
    assert all(p is not None for p in packets)
    ev = _rechunked([p for p in packets if p is not None], "evt3", sensor.geometry)
    extra = sensor.stats().extra
    assert (extra["loop_us"], extra["recorded_us"]) == (8192, 8811)
    assert not any(v for k, v in extra.items() if k.startswith("decoder_skipped"))
    assert ev.is_time_sorted()
    passes = (ev.t - t0) // 8192
    n_full = int(passes[-1])  # the last pass may be cut short
    assert n_full >= 5
    counts = np.bincount(passes)[:n_full]
    assert (counts == per_pass).all()
    ref = whole.events[:per_pass]
    for k in range(n_full):
        got = ev[k * per_pass : (k + 1) * per_pass]
        np.testing.assert_array_equal(got.t, ref.t + k * 8192)
        np.testing.assert_array_equal(got.x, ref.x)
        np.testing.assert_array_equal(got.y, ref.y)
    assert extra["passes"] >= n_full


@needs_data
def test_evt2_replays_its_wire_bytes() -> None:
    path = DATA / "evt2_gen3_sample.raw"
    sensor = FileEventSensor(path, chunk_bytes=65_536)
    assert sensor.wire
    sensor.start()
    packets = _drain(sensor, 0.0)
    ev = _rechunked(packets, "evt2", sensor.geometry)
    assert len(ev) == 539_481


def test_loop_refuses_what_cannot_loop(tmp_path: Path) -> None:
    t = np.arange(100, 3_000, 100, dtype=np.int64)  # less than one whole TIME_HIGH period
    ev = EventArray.from_arrays(np.zeros_like(t), np.zeros_like(t), np.ones_like(t), t)
    path = tmp_path / "short.raw"
    write_raw(path, RawHeader(fmt="evt3", width=64, height=64), ev)
    sensor = open_device("event_sensor", f"file://{path}?loop=1")
    with pytest.raises(ConfigError, match="whole TIME_HIGH period"):
        sensor.start()


def test_burst_pace_is_piecewise_and_invertible() -> None:
    pace = Pace(0.5, burst_at_s=2.0, burst_s=1.0, burst_pace=4.0)
    assert pace.stream_us(1.0) == 500_000
    assert pace.stream_us(2.5) == 1_000_000 + 2_000_000
    assert pace.stream_us(4.0) == 1_000_000 + 4_000_000 + 500_000
    for s in (0.3, 2.0, 2.7, 3.9):
        assert pace.host_s(pace.stream_us(s)) == pytest.approx(s, abs=1e-6)
    with pytest.raises(ConfigError, match="burst"):
        Pace(0.0, burst_at_s=1.0, burst_s=1.0, burst_pace=2.0)
    with pytest.raises(ConfigError, match="START_S:LEN_S:PACE"):
        open_device("event_sensor", f"file://{DATA / 'evt3_pedestrians.raw'}?pace=1&burst=1:2")


@needs_data
@pytest.mark.parametrize("pace", [0.8, 0.3])
def test_looped_stream_keeps_real_time_below_pace_one(pace: float) -> None:
    """A device's clock never runs slow: at pace < 1 the looped passes are spaced out by quiet
    TIME_HIGH periods, so the events come at pace x the recording's rate on a real-time clock
    (a window gate placing them by host time sees a clock that keeps up)."""
    path = DATA / "evt3_gen41_sample.raw"
    _, whole = read_raw(path)
    t0 = int(whole.events.t[0])
    per_pass = int(np.count_nonzero(whole.events.t < t0 + 8192))
    ref = whole.events[:per_pass]
    clock = FakeClock()
    sensor = FileEventSensor(path, pace=pace, loop=True, clock=clock, sleep=clock.sleep)
    sensor.start()
    start = clock.now
    packets = []
    while clock.now - start < 0.4:
        p = sensor.read_events(0.01)
        if p is not None:
            packets.append(p)
        clock.now += 0.0005  # the reader's own time between reads
    ev = _rechunked(packets, "evt3", sensor.geometry)
    assert not any(v for k, v in sensor.stats().extra.items() if k.startswith("decoder_skipped"))
    n_pass = len(ev) // per_pass
    starts = []
    for k in range(n_pass):
        got = ev[k * per_pass : (k + 1) * per_pass]
        np.testing.assert_array_equal(got.x, ref.x)
        shift = got.t - ref.t
        assert (shift == shift[0]).all()
        starts.append(int(shift[0]))
    steps = np.diff(starts)
    assert set(steps.tolist()) <= {8192 + 4096 * q for q in range(8)}  # whole quiet periods between
    assert float(np.mean(steps)) == pytest.approx(8192 / pace, rel=0.08)
    # real time: the stream time handed out follows the host clock, not pace x it
    assert (int(ev.t[-1]) - t0) / 1e6 == pytest.approx(clock.now - start, abs=0.012)


def test_real_clock_pace_runs_no_slower_than_the_host() -> None:
    pace = Pace(0.4, burst_at_s=2.0, burst_s=1.0, burst_pace=2.0, real_clock=True)
    assert pace.stream_us(1.0) == 1_000_000  # thinned, not slowed
    assert pace.stream_us(2.5) == 2_000_000 + 1_000_000  # a burst above 1 runs the clock faster
    assert pace.density(500_000) == 0.4
    assert pace.density(2_500_000) == 1.0
    for s in (0.3, 2.0, 2.7, 3.9):
        assert pace.host_s(pace.stream_us(s)) == pytest.approx(s, abs=1e-6)
    assert Pace(0.4).density(500_000) == 1.0  # an unlooped replay slows its clock instead
