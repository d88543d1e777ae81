"""Event sensors stored as EVT words: write, finalize and read back exactly what was decoded.

The same packets go through a take stored as words and one stored as columns: every reader
call must agree, on the real Gen4.1 recording and on synthetic streams with a window clip.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest

from drivers.testing.evt_packets import packets_from_bytes, packets_of
from drivers.testing.evt_streams import assert_same, needs_data, real_body
from rigd.core.devices import DeviceInfo
from rigd.core.errors import TakeError, WriteDeferredError
from rigd.core.events import EventArray, EventPacket, TriggerEvents
from rigd.core.schema import SyncReport
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.take import TakeWriter, open_take
from rigd.take.seal import fail_take, finalize_take, set_window

CMAP = ClockMap(device_ref_us=400_000, rig_ref_us=5_000_000, rate=0.999905, frac_us=-0.4)
REPORT = SyncReport(rate_hz=30.0, n_pulses=0, t_first_pulse_us=None, t_last_pulse_us=None)


def write(
    path: Path,
    packets: list[EventPacket],
    storage: str,
    *,
    width: int = 1280,
    height: int = 720,
    window: tuple[int | None, int | None] = (None, None),
    finalize: bool = True,
    flush_every: int = 7,
) -> None:
    cfg = WriterConfig(event_storage=storage, fsync=False)  # type: ignore[arg-type]
    w = TakeWriter(path, rig_config_json="{}", take_id="t", config=cfg, rigd_version="t")
    w.add_event_sensor(
        "ev0", DeviceInfo(kind="event_sensor", spec="sim://t/ev0"), width, height, "{}", "evt3"
    )
    for i, p in enumerate(packets):
        w.append_packet("ev0", p)
        if i % flush_every == flush_every - 1:
            w.flush()
    if window != (None, None):
        set_window(w, window[0], window[1], 0, {})
    if finalize:
        finalize_take(w, {"ev0": CMAP}, {}, REPORT)
    w.close()


def rig(ev: EventArray) -> EventArray:
    return ev.with_time(CMAP.to_rig(ev.t))


@pytest.fixture(scope="module")
def synthetic() -> tuple[EventArray, list[EventPacket]]:
    rng = np.random.default_rng(3)
    n = 120_000
    t = 400_000 + np.cumsum(rng.integers(0, 25, n))
    ev = EventArray.from_arrays(rng.integers(0, 640, n), rng.integers(0, 480, n), rng.integers(0, 2, n), t)
    ev = ev[np.lexsort((ev.x, ev.p, ev.y, ev.t))]
    return ev, packets_of(ev, 9_000, width=640, height=480)


def test_words_and_columns_read_the_same(
    tmp_path: Path, synthetic: tuple[EventArray, list[EventPacket]]
) -> None:
    ev, packets = synthetic
    lo, hi = CMAP.to_rig(np.array([500_000, 2_800_000]))
    paths = {s: tmp_path / f"{s}.h5" for s in ("evt_words", "columns")}
    for storage, path in paths.items():
        write(path, packets, storage, width=640, height=480)
    with open_take(paths["evt_words"]) as words, open_take(paths["columns"]) as cols:
        with h5py.File(paths["evt_words"]) as f:
            assert f["events/ev0"].attrs["storage"] == "evt_words"
            assert "x" not in f["events/ev0"]
        assert words.sensor("ev0").count == cols.sensor("ev0").count == len(ev)
        assert_same(words.sensor("ev0").events(), rig(ev))
        assert_same(words.sensor("ev0").events(int(lo), int(hi)), cols.sensor("ev0").events(int(lo), int(hi)))
        assert_same(words.sensor("ev0").events(int(lo)), cols.sensor("ev0").events(int(lo)))
        assert_same(words.sensor("ev0").events(None, int(hi)), cols.sensor("ev0").events(None, int(hi)))
        for t in (0, int(lo), int(lo) + 1, int(hi), 10**12):
            assert words.sensor("ev0").index(t) == cols.sensor("ev0").index(t)
        assert_same(words.sensor("ev0").by_index(1234, 56789), cols.sensor("ev0").by_index(1234, 56789))
        assert words.sensor("ev0").span == cols.sensor("ev0").span
        o1, c1 = words.sensor("ev0").histogram(10_000)
        o2, c2 = cols.sensor("ev0").histogram(10_000)
        assert o1 == o2
        np.testing.assert_array_equal(c1, c2)
        a = list(words.sensor("ev0").iter(50_000))
        b = list(cols.sensor("ev0").iter(50_000))
        assert len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            assert_same(x, y)


def test_window_clips_what_a_straddling_packet_brought(
    tmp_path: Path, synthetic: tuple[EventArray, list[EventPacket]]
) -> None:
    """Packets across the window's edges are stored whole; the reader shows the window only,
    and finalize counted exactly the events inside it."""
    ev, packets = synthetic
    lo, hi = (int(v) for v in CMAP.to_rig(np.array([700_003, 1_900_007])))
    write(tmp_path / "w.h5", packets, "evt_words", width=640, height=480, window=(lo, hi))
    inside = rig(ev)
    inside = inside[(inside.t >= lo) & (inside.t < hi)]
    with open_take(tmp_path / "w.h5") as take:
        assert take.sensor("ev0").count == len(inside)
        assert_same(take.sensor("ev0").events(), inside)
        assert_same(take.sensor("ev0").events(lo - 10_000, lo + 20_000), inside[inside.t < lo + 20_000])
        assert take.sensor("ev0").span == (int(inside.t[0]), int(inside.t[-1]))
        assert int(take.sensor("ev0").histogram(1000)[1].sum()) == len(inside)
    # What was stored but lies outside the window is written down: stored = before + in + after.
    all_rig = rig(ev)
    with h5py.File(tmp_path / "w.h5") as f:
        outside = json.loads(f.attrs["window_outside_json"])["ev0"]
    assert outside["stored_before"] == int(np.count_nonzero(all_rig.t < lo))
    assert outside["stored_after"] == int(np.count_nonzero(all_rig.t >= hi))
    assert outside["stored_before"] + len(inside) + outside["stored_after"] == len(ev)


@needs_data
def test_real_gen41_stream_round_trips(tmp_path: Path) -> None:
    data = real_body("evt3_gen41_sample.raw")
    packets = list(packets_from_bytes("evt3", data, 48_000))
    whole = EventArray.concatenate([p.events for p in packets])
    write(tmp_path / "r.h5", packets, "evt_words", flush_every=3)
    with open_take(tmp_path / "r.h5") as take:
        assert_same(take.sensor("ev0").events(), rig(whole))
        with h5py.File(tmp_path / "r.h5") as f:
            stored = f["events/ev0/evt_words"]
            assert stored.shape[0] == sum(len(p.raw.data) for p in packets if p.raw is not None)
            assert stored.id.get_storage_size() / len(whole) <= 2.5


@needs_data
def test_words_stored_uncompressed_while_behind_read_the_same(tmp_path: Path) -> None:
    """Scanned packets (events never decoded on the way in), their chunks stored uncompressed for
    a while (the writer behind): the take reads the same events, only its bytes grew."""
    data = real_body("evt3_gen41_sample.raw")
    packets = list(packets_from_bytes("evt3", data, 16_000, scan=True))
    assert sum(p.from_scan for p in packets) >= len(packets) - 2
    whole = EventArray.concatenate([p.events for p in packets])
    cfg = WriterConfig(fsync=False)
    w = TakeWriter(tmp_path / "u.h5", rig_config_json="{}", take_id="t", config=cfg, rigd_version="t")
    w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="sim://t/ev0"), 1280, 720, "{}", "evt3")
    third = len(packets) // 3
    for i, p in enumerate(packets):
        w.compress_events(not third <= i < 2 * third)
        w.append_packet("ev0", p)
        if i % 5 == 4:
            w.flush()
    finalize_take(w, {"ev0": CMAP}, {}, REPORT)
    w.close()
    with open_take(tmp_path / "u.h5") as take:
        assert_same(take.sensor("ev0").events(), rig(whole))
    with h5py.File(tmp_path / "u.h5") as f:
        words = f["events/ev0/evt_words"]
        masks = [words.id.get_chunk_info(i).filter_mask for i in range(words.id.get_num_chunks())]
        assert set(masks) == {0, 1}
        np.testing.assert_array_equal(
            np.asarray(words), np.frombuffer(b"".join(p.raw.data for p in packets), np.uint8)
        )


def test_unfinalized_take_reads_in_device_time_with_its_tail(
    tmp_path: Path, synthetic: tuple[EventArray, list[EventPacket]]
) -> None:
    """A take whose writer died after a flush: the flushed words (tail slot included) read back."""
    ev, packets = synthetic
    path = tmp_path / "u.h5"
    cfg = WriterConfig(event_storage="evt_words", fsync=False)
    w = TakeWriter(path, rig_config_json="{}", take_id="t", config=cfg, rigd_version="t")
    w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="s"), 640, 480, "{}", "evt3")
    for p in packets[:5]:
        w.append_packet("ev0", p)
    w.flush()
    with open_take(path) as take:
        n = sum(len(p.events) for p in packets[:5])
        assert take.sensor("ev0").count == n
        assert_same(take.sensor("ev0").events(), ev[:n])
    w.close()


def test_bad_batch_is_refused_whole(tmp_path: Path, synthetic: tuple[EventArray, list[EventPacket]]) -> None:
    _ev, packets = synthetic
    cfg = WriterConfig(event_storage="evt_words", fsync=False)
    path = tmp_path / "b.h5"
    w = TakeWriter(path, rig_config_json="{}", take_id="t", config=cfg, rigd_version="t")
    w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="s"), 100, 480, "{}", "evt3")
    with pytest.raises(TakeError, match="outside the sensor's 100x480 geometry"):
        w.append_packet("ev0", packets[0])
    w.close()
    with open_take(path) as take:
        assert take.sensor("ev0").count == 0


def test_refused_batch_mid_stream_leaves_no_bytes(
    tmp_path: Path, synthetic: tuple[EventArray, list[EventPacket]]
) -> None:
    """A batch refused mid-stream (time going back): its words are not stored and the next
    row decodes from its own state; every other packet reads back exactly."""
    _, packets = synthetic
    cfg = WriterConfig(event_storage="evt_words", fsync=False)
    path = tmp_path / "m.h5"
    w = TakeWriter(path, rig_config_json="{}", take_id="t", config=cfg, rigd_version="t")
    w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="s"), 640, 480, "{}", "evt3")
    for p in packets[:6]:
        w.append_packet("ev0", p)
    with pytest.raises(TakeError, match="before the previous event"):
        w.append_packet("ev0", packets[2])
    for p in packets[6:]:
        w.append_packet("ev0", p)
    finalize_take(w, {"ev0": CMAP}, {}, REPORT)
    w.close()
    with open_take(path) as take, h5py.File(path) as f:
        index = f["events/ev0/evt_index"][...]
        assert index[1:, 6].min() == 0  # the row after the refused batch does not follow on
        assert f["events/ev0/evt_words"].shape[0] == sum(len(p.raw.data) for p in packets if p.raw)
        assert_same(take.sensor("ev0").events(), rig(EventArray.concatenate([p.events for p in packets])))


@pytest.mark.parametrize("fmt", [None, "dat"])
def test_sensor_without_words_falls_back_to_columns(
    tmp_path: Path, fmt: str | None, synthetic: tuple[EventArray, list[EventPacket]]
) -> None:
    ev, _ = synthetic
    path = tmp_path / "c.h5"
    w = TakeWriter(
        path, rig_config_json="{}", take_id="t", config=WriterConfig(fsync=False), rigd_version="t"
    )
    w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="s"), 640, 480, "{}", fmt)
    w.append_packet("ev0", EventPacket(ev[:1000], TriggerEvents.empty(), 0))
    w.close()
    with h5py.File(path) as f:
        g = f["events/ev0"]
        assert g.attrs["storage"] == "columns"
        assert "EVT words" in g.attrs["storage_note"]
        assert g["t"].shape == (1000,)


def test_both_stores_answer_the_writer_alike(
    tmp_path: Path, synthetic: tuple[EventArray, list[EventPacket]]
) -> None:
    """The writer asks a sensor's store, never its class: the same packets give the same
    first time, counts and events in the take through either store, whichever class
    `event_store` chose."""
    ev, packets = synthetic
    seen = {}
    for storage in ("evt_words", "columns"):
        cfg = WriterConfig(event_storage=storage, fsync=False)  # type: ignore[arg-type]
        path = tmp_path / f"{storage}.h5"
        w = TakeWriter(path, rig_config_json="{}", take_id="t", config=cfg, rigd_version="t")
        w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="s"), 640, 480, "{}", "evt3")
        store = w.state.stores["ev0"]
        assert store.first_time() is None
        assert store.n_written == 0
        for i, p in enumerate(packets):
            # words: stored as they are while "behind", the last chunk too; columns: nothing to switch
            w.compress_events(i < 5)
            w.append_packet("ev0", p)
        w.flush()
        first = store.first_time()
        if storage == "evt_words":
            with pytest.raises(TakeError, match="'ev0' stores EVT words: use append_packet"):
                w.append_events("ev0", ev[:10])
        finalize_take(w, {"ev0": CMAP}, {}, REPORT)
        seen[storage] = (type(store).__name__, first, store.n_written, w.events_in_take())
        w.close()
    assert seen["evt_words"][0] == "EvtWordsSink"
    assert seen["columns"][0] == "EventSink"
    assert seen["evt_words"][1:] == seen["columns"][1:] == (int(ev.t[0]), len(ev), {"ev0": len(ev)})
    with open_take(tmp_path / "evt_words.h5") as words, open_take(tmp_path / "columns.h5") as cols:
        assert_same(words.sensor("ev0").events(), cols.sensor("ev0").events())


def test_re_tied_clock_shift_is_applied_on_read(
    tmp_path: Path, synthetic: tuple[EventArray, list[EventPacket]]
) -> None:
    """A restarted clock re-tied by the capture path: the packets' times carry the shift, their
    words do not; the chunk's shift_us says so and the reader adds it back."""
    _, packets = synthetic
    shift = 7_000_000
    later = []
    for p in packets[5:]:
        assert p.raw is not None
        raw = dataclasses.replace(p.raw, shift_us=shift)
        later.append(EventPacket(p.events.with_time(p.events.t + shift), p.triggers, 0, raw))
    moved = packets[:5] + later
    write(tmp_path / "s.h5", moved, "evt_words", width=640, height=480)
    with open_take(tmp_path / "s.h5") as take, h5py.File(tmp_path / "s.h5") as f:
        assert set(f["events/ev0/evt_index"][:, 5].tolist()) == {0, shift}
        assert_same(take.sensor("ev0").events(), rig(EventArray.concatenate([p.events for p in moved])))


def test_chunks_carry_their_decoders_geometry_and_a_take_of_another_one_checks_again(
    tmp_path: Path, synthetic: tuple[EventArray, list[EventPacket]]
) -> None:
    """The decoder emits no event outside its width x height, so a take of that geometry skips
    the writer's x/y check; a take of any other geometry still refuses what lies outside it."""
    _ev, packets = synthetic
    assert all(p.raw is not None and p.raw.geometry == (640, 480) for p in packets)
    cfg = WriterConfig(event_storage="evt_words", fsync=False)
    w = TakeWriter(tmp_path / "g.h5", rig_config_json="{}", take_id="t", config=cfg, rigd_version="t")
    w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="s"), 640, 400, "{}", "evt3")
    with pytest.raises(TakeError, match=r"y=4\d\d outside the sensor's 640x400 geometry"):
        w.append_packet("ev0", packets[0])
    w.close()


def _fill(disk: Path, leave: int = 0) -> Path:
    """Take every free byte of `disk` but `leave` into one file (what another writer would do)."""
    ballast = disk / "ballast"
    fd = os.open(ballast, os.O_WRONLY | os.O_CREAT)
    try:
        for block in (1 << 16, 1 << 12, 1):  # to the last page
            with pytest.raises(OSError, match="No space left") as full:  # noqa: PT012 - until full
                while os.write(fd, bytes(block)):
                    pass
            assert full.value.errno == errno.ENOSPC, full.value
        if leave:
            os.ftruncate(fd, os.fstat(fd).st_size - leave)
    finally:
        os.close(fd)
    return ballast


@pytest.mark.parametrize("storage", ["evt_words", "columns"])
def test_what_a_full_disk_refused_is_stored_and_indexed_once_there_is_room(
    tmp_path: Path,
    synthetic: tuple[EventArray, list[EventPacket]],
    mount_tmpfs: Callable[[str], Path],
    storage: str,
) -> None:
    """On a real full disk (not a mocked write): HDF5 notes where a new chunk goes before writing
    it and indexes it only after; the retry `fail` makes in the room the ballast left must not
    reuse that note, or the chunk is written but never indexed and reads back as zeros. The
    packet whose write failed is the take's (`WriteDeferredError`), its trigger edges too."""
    packets = [
        EventPacket(
            p.events,
            TriggerEvents(p.events.t[:1].copy(), np.ones(1, np.uint8), np.zeros(1, np.uint8)),
            p.host_time_ns,
            p.raw,
        )
        for p in synthetic[1]
    ]
    disk = mount_tmpfs("4m")
    path = disk / "full.h5"
    w = TakeWriter(
        path, rig_config_json="{}", take_id="t", config=WriterConfig(event_storage=storage), rigd_version="t"
    )
    w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="sim://t/ev0"), 640, 480, "{}", "evt3")
    w.flush()
    ballast = _fill(disk)
    appended = 0
    with pytest.raises(OSError, match="No space left") as failed:  # noqa: PT012 - fills in the loop
        for p in packets:
            appended += 1
            w.append_packet("ev0", p)
            if storage == "columns" and appended % 4 == 0:  # columns reach the disk on a flush
                w.flush()
    assert failed.value.errno == errno.ENOSPC
    assert isinstance(failed.value, WriteDeferredError) == (storage == "evt_words")
    ballast.unlink()
    fail_take(w, "disk full")
    w.close()
    with open_take(path) as take:
        assert take.status == "failed"
        got = take.sensor("ev0").events()
        edges = take.sensor("ev0").triggers
    want = EventArray.concatenate([p.events for p in packets[:appended]])
    np.testing.assert_array_equal(got.t, want.t)
    np.testing.assert_array_equal(got.x, want.x)
    np.testing.assert_array_equal(edges.t, [p.events.t[0] for p in packets[:appended]])


@pytest.mark.parametrize(("before", "left"), [(5, 65536), (20, 16384), (40, 16384)])
def test_columns_a_full_disk_stopped_mid_flush_read_back_whole(
    tmp_path: Path, mount_tmpfs: Callable[[str], Path], before: int, left: int
) -> None:
    """Columns reach the disk at flushes. With HDF5's chunk cache, a chunk whose flush the full
    disk refused was written again by `fail` but never indexed: 4,096 event times read back as
    0, silently, in each of these three cases. The writer keeps no chunk cache (a write fails at
    its call, and its retry is indexed): the take reads back every event it counted."""
    rng = np.random.default_rng(3)
    n = 200_000
    t = 400_000 + np.cumsum(rng.integers(0, 25, n))
    ev = EventArray.from_arrays(rng.integers(0, 640, n), rng.integers(0, 480, n), rng.integers(0, 2, n), t)
    packets = packets_of(ev[np.lexsort((ev.x, ev.p, ev.y, ev.t))], 4000, width=640, height=480)
    disk = mount_tmpfs("8m")
    path = disk / "full.h5"
    cfg = WriterConfig(event_storage="columns", event_chunk=4096)
    w = TakeWriter(path, rig_config_json="{}", take_id="t", config=cfg, rigd_version="t")
    w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="sim://t/ev0"), 640, 480, "{}", "evt3")
    for p in packets[:before]:
        w.append_packet("ev0", p)
    w.flush()
    ballast = _fill(disk, leave=left)
    appended = before
    with pytest.raises(OSError, match=r"No space left|Unable to"):  # noqa: PT012 - fills in the loop
        for i, p in enumerate(packets[before:]):
            w.append_packet("ev0", p)
            appended += 1
            if i % 3 == 2:
                w.flush()
    ballast.unlink()
    fail_take(w, "disk full")
    w.close()
    with open_take(path) as take:
        got = take.sensor("ev0").events()
    want = EventArray.concatenate([p.events for p in packets[:appended]])
    assert len(got) == len(want)
    bad = np.flatnonzero(got.t != want.t)
    assert not len(bad), f"{len(bad)} event times differ from index {bad[0]}: {got.t[bad[:3]]}"


def test_a_chunk_write_that_fails_leaves_the_take_to_be_marked_failed(
    tmp_path: Path, synthetic: tuple[EventArray, list[EventPacket]], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The capture keeps the disk-full error (and with it the failed call's arguments) until the
    take is marked failed: nothing the failed write held may stop `fail` and `close`, and what
    `fail` then writes (in the room the ballast made) agrees with its index, to the event."""
    from rigd.take.evt_sink import EvtWordsSink

    _, packets = synthetic
    path = tmp_path / "full.h5"
    cfg = WriterConfig(fsync=False)
    w = TakeWriter(path, rig_config_json="{}", take_id="t", config=cfg, rigd_version="t")
    w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="sim://t/ev0"), 640, 480, "{}", "evt3")
    written = EvtWordsSink._write_chunk
    calls: list[int] = []

    def second_chunk_fills_the_disk(self: EvtWordsSink, data: bytes, offset: int) -> None:
        calls.append(offset)
        if len(calls) >= 2:
            raise OSError(28, "No space left on device")
        written(self, data, offset)

    monkeypatch.setattr(EvtWordsSink, "_write_chunk", second_chunk_fills_the_disk)
    appended = 0
    with pytest.raises(OSError, match="No space left") as kept:  # noqa: PT012 - fills in the loop
        for p in packets:
            appended += 1
            w.append_packet("ev0", p)
    monkeypatch.setattr(EvtWordsSink, "_write_chunk", written)
    assert kept.value.__traceback__ is not None  # held, as the capture holds its error
    assert 1 < appended < len(packets)
    fail_take(w, "disk full")
    w.close()
    with open_take(path) as take:
        assert take.status == "failed"
        got = take.sensor("ev0").events()
    want = EventArray.concatenate([p.events for p in packets[:appended]])
    np.testing.assert_array_equal(got.t, want.t)
    np.testing.assert_array_equal(got.x, want.x)
