"""Time windows of an EVT words sensor, read the fast way (chunks decompressed as stored, the last
row decoded only as far as the window reaches, rig time mapped by a compiled kernel): the same
events as a plain-h5py read of the same packets stored in the DSEC layout, and each piece the same
as what it replaces."""

from __future__ import annotations

from pathlib import Path

import h5py
import hdf5plugin
import numpy as np
import pytest
import zstandard

from drivers.testing.evt_packets import packets_of
from drivers.testing.evt_streams import assert_same
from rigd.core.devices import DeviceInfo
from rigd.core.errors import TakeError, TakeFormatError
from rigd.core.events import EventArray, EventPacket
from rigd.core.schema import SyncReport
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.take import TakeWriter, evt_read, open_take
from rigd.take.evt_read import WordBytes, _to_rig
from rigd.take.seal import finalize_take

CMAP = ClockMap(device_ref_us=400_000, rig_ref_us=5_000_000, rate=1.000187, frac_us=0.37)
REPORT = SyncReport(rate_hz=30.0, n_pulses=0, t_first_pulse_us=None, t_last_pulse_us=None)
W, H = 640, 480


def write(path: Path, packets: list[EventPacket], storage: str) -> None:
    cfg = WriterConfig(event_storage=storage, fsync=False)  # type: ignore[arg-type]
    w = TakeWriter(path, rig_config_json="{}", take_id="t", config=cfg, rigd_version="t")
    w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="sim://t/ev0"), W, H, "{}", "evt3")
    for i, p in enumerate(packets):
        w.append_packet("ev0", p)
        if i % 5 == 4:
            w.flush()
    finalize_take(w, {"ev0": CMAP}, {}, REPORT)
    w.close()


def plain_h5py_window(path: Path, t0: int, t1: int) -> EventArray:
    """A window of the DSEC layout (x, y, p, t, ms_to_idx, t_offset) read with h5py alone, the
    way EventSlicer does: the ms index to a conservative range, then the exact edges in t."""
    with h5py.File(path, "r") as f:
        g = f["events/ev0"]
        off = int(g["t_offset"][()])
        ms, t_all = g["ms_to_idx"][()], g["t"]
        n = t_all.shape[0]
        a, b = (t0 - off) // 1000, -(-(t1 - off) // 1000)
        lo = 0 if a < 0 else (n if a >= len(ms) else int(ms[a]))
        hi = n if max(b, 0) >= len(ms) else int(ms[max(b, 0)])
        t = t_all[lo:hi].astype(np.int64)
        i = lo + int(np.searchsorted(t, t0 - off))
        j = max(i, lo + int(np.searchsorted(t, t1 - off)))
        return EventArray(
            g["x"][i:j].astype(np.uint16),
            g["y"][i:j].astype(np.uint16),
            g["p"][i:j].astype(np.int8) * np.int8(2) - np.int8(1),
            g["t"][i:j].astype(np.int64) + off,
        )


@pytest.fixture(scope="module")
def takes(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, EventArray]:
    """The same packets stored as EVT words and as DSEC columns; rows of several ms, a drifting
    clock; bursts, so that events are not even in time within a row."""
    rng = np.random.default_rng(11)
    n = 400_000
    rate = 1 + 0.9 * np.sin(np.linspace(0, 40 * np.pi, n))
    t = 400_000 + np.cumsum(rng.exponential(8.0 * rate + 0.05)).astype(np.int64)
    ev = EventArray.from_arrays(rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, 2, n), t)
    ev = ev[np.lexsort((ev.x, ev.p, ev.y, ev.t))]
    packets = packets_of(ev, 24_000, width=W, height=H)
    root = tmp_path_factory.mktemp("windows")
    write(root / "words.h5", packets, "evt_words")
    write(root / "columns.h5", packets, "columns")
    return root / "words.h5", root / "columns.h5", ev.with_time(CMAP.to_rig(ev.t))


def _windows(rig: EventArray, k: int, seed: int) -> list[tuple[int, int]]:
    rng = np.random.default_rng(seed)
    first, last = int(rig.t[0]), int(rig.t[-1])
    starts = rng.integers(first - 3_000, last + 3_000, k)
    lengths = rng.choice([1, 7, 999, 1_000, 50_000, 50_001, 333_333], k)
    fixed = [(first, first + 50_000), (last - 50_000, last), (last, last + 1), (first - 10, first + 1)]
    return fixed + [(int(s), int(s) + int(w)) for s, w in zip(starts, lengths, strict=True)]


@pytest.mark.parametrize("margin", [evt_read._CUT_MARGIN, 0.0, -0.5])
def test_windows_match_a_plain_h5py_read_of_the_dsec_layout(
    takes: tuple[Path, Path, EventArray], margin: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Margins 0 and -1/2 make the cut at the last row fall short of the window's end now and
    then, so the rest of the row must be read and decoded after all: still the same events."""
    words, columns, rig = takes
    monkeypatch.setattr(evt_read, "_CUT_MARGIN", margin)
    with open_take(words) as take:
        series = take.sensor("ev0")
        assert series.storage == "evt_words"
        for t0, t1 in _windows(rig, 120, seed=abs(int(margin * 100)) + 1):
            got = series.events(t0, t1)
            assert_same(got, plain_h5py_window(columns, t0, t1))
            assert_same(got, rig[(rig.t >= t0) & (rig.t < t1)])


def test_a_row_cut_short_stops_decoding_and_one_cut_too_short_reads_on(
    takes: tuple[Path, Path, EventArray], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Both ways through `_decode_until` are taken by the windows above."""
    words, _, rig = takes
    calls: list[bool] = []
    real = evt_read.EvtWordsEvents._decode_until

    def spy(self: evt_read.EvtWordsEvents, *args: object) -> tuple[EventArray, bool]:
        ev, whole = real(self, *args)  # type: ignore[arg-type]
        calls.append(whole)
        return ev, whole

    monkeypatch.setattr(evt_read.EvtWordsEvents, "_decode_until", spy)
    with open_take(words) as take:
        for margin in (evt_read._CUT_MARGIN, -0.5):
            monkeypatch.setattr(evt_read, "_CUT_MARGIN", margin)
            for t0, t1 in _windows(rig, 60, seed=5):
                take.sensor("ev0").events(t0, t1)
    assert True in calls
    assert False in calls


@pytest.mark.parametrize(
    "cmap",
    [
        CMAP,
        ClockMap(0, 0, 1.0, 0.0),
        ClockMap(-7, 2**40, 0.9997, -0.5),
        ClockMap(123_456_789_012, 5, 1.000301, 0.49999),
    ],
)
def test_compiled_rig_map_is_the_clock_maps_to_the_bit(cmap: ClockMap) -> None:
    rng = np.random.default_rng(2)
    t = np.concatenate(
        [
            rng.integers(-(2**40), 2**40, 200_000),
            cmap.device_ref_us + rng.integers(-5_000_000, 5_000_000, 200_000),
            cmap.device_ref_us + np.arange(-2_000, 2_000),
        ]
    ).astype(np.int64)
    got = _to_rig(t, cmap.device_ref_us, cmap.rig_ref_us, cmap.rate, cmap.frac_us)
    np.testing.assert_array_equal(got, cmap.to_rig(t))
    assert _to_rig(t[:0], 0, 0, 1.0, 0.0).shape == (0,)


@pytest.mark.parametrize("keep", [evt_read._KEEP_BUFFER, 9_000])
@pytest.mark.parametrize("mapped", [False, True])
def test_word_bytes_read_what_h5py_reads(
    tmp_path: Path, mapped: bool, keep: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Zstd chunks (one stored uncompressed, filter mask bit 0, one never written), a gzip and
    a contiguous dataset, through HDF5 or the mapped file, with the kept buffer's bound as it is
    and small (reads longer than it, a buffer that grows): every range the same as h5py's slice,
    across chunk edges, in any order; a result stays valid until the next read only."""
    monkeypatch.setattr(evt_read, "_KEEP_BUFFER", keep)
    rng = np.random.default_rng(4)
    size, chunk = 10 * 4096, 4096
    data = (rng.integers(0, 16, size) * 3).astype(np.uint8)  # compressible
    with h5py.File(tmp_path / "w.h5", "w") as f:
        z = f.create_dataset("zstd", shape=(size,), dtype="u1", chunks=(chunk,), **hdf5plugin.Zstd(clevel=1))
        z[: 6 * chunk] = data[: 6 * chunk]
        z.id.write_direct_chunk((6 * chunk,), data[6 * chunk : 7 * chunk].tobytes(), filter_mask=1)
        z[8 * chunk :] = data[8 * chunk :]  # chunk 7 never written
        f.create_dataset("gzip", data=data, chunks=(chunk,), compression="gzip")
        f.create_dataset("plain", data=data)
    with h5py.File(tmp_path / "w.h5", "r") as f:
        readers = {
            name: WordBytes(f[name], f"w.h5/{name}", mapped=mapped) for name in ("zstd", "gzip", "plain")
        }
        assert (readers["zstd"]._map is not None) == mapped
        assert readers["zstd"].direct
        assert not readers["gzip"].direct
        assert not readers["plain"].direct
        edges = [0, 1, chunk - 1, chunk, 6 * chunk + 5, 7 * chunk, 7 * chunk + 9, 8 * chunk, size - 1, size]
        ranges = [(a, b) for a in edges for b in edges if a <= b]
        ranges += [tuple(sorted(rng.integers(0, size + 1, 2).tolist())) for _ in range(200)]
        for name, reader in readers.items():
            for a, b in ranges:
                np.testing.assert_array_equal(reader.read(a, b), f[name][a:b], err_msg=f"{name} [{a}, {b})")
        # in order, overlapping, going on inside a chunk, and back: what a run of windows asks
        pos = 0
        while pos < size:
            a = max(0, pos - int(rng.integers(0, 6000)))
            b = min(size, pos + int(rng.integers(1, 9000)))
            for name, reader in readers.items():
                np.testing.assert_array_equal(
                    reader.read(a, b), data[a:b] if name != "zstd" else f[name][a:b]
                )
            pos = b
        kept = readers["zstd"].read(100, 5000).copy()
        np.testing.assert_array_equal(kept, data[100:5000])


@pytest.mark.parametrize("stored", [b"\x00" * 300, None])
def test_a_damaged_words_chunk_is_a_format_error_naming_it(tmp_path: Path, stored: bytes | None) -> None:
    """Garbage where a zstd frame should be, or a frame of the wrong chunk's length."""
    chunk = 4096
    data = np.arange(3 * chunk, dtype=np.uint32).astype(np.uint8)
    with h5py.File(tmp_path / "d.h5", "w") as f:
        z = f.create_dataset(
            "zstd", shape=data.shape, dtype="u1", chunks=(chunk,), **hdf5plugin.Zstd(clevel=1)
        )
        z[...] = data
        bad = stored if stored is not None else zstandard.ZstdCompressor().compress(data[:100].tobytes())
        z.id.write_direct_chunk((chunk,), bad, filter_mask=0)
    with h5py.File(tmp_path / "d.h5", "r") as f:
        reader = WordBytes(f["zstd"], "d.h5")
        np.testing.assert_array_equal(reader.read(0, chunk), data[:chunk])
        with pytest.raises(TakeFormatError, match=f"d.h5/evt_words: the chunk at byte {chunk} "):
            reader.read(10, chunk + 200)


def test_a_mapped_reader_of_a_closed_take_refuses_and_one_with_a_user_block_is_not_mapped(
    takes: tuple[Path, Path, EventArray], tmp_path: Path
) -> None:
    words, _, rig = takes
    t0 = int(rig.t[len(rig) // 2])
    with open_take(words) as take:
        series = take.sensor("ev0")
        assert len(series.events(t0, t0 + 20_000)) > 0
        reader = series._words()._bytes  # type: ignore[union-attr]
        assert reader._map is not None
    with pytest.raises(TakeError):
        series.events(t0, t0 + 20_000)
    data = np.arange(50_000, dtype=np.uint32).astype(np.uint8)
    with h5py.File(tmp_path / "u.h5", "w", userblock_size=512) as f:
        f.create_dataset("zstd", data=data, chunks=(4096,), **hdf5plugin.Zstd(clevel=1))
    with h5py.File(tmp_path / "u.h5", "r") as f:
        reader = WordBytes(f["zstd"], "u.h5", mapped=True)
        assert reader._map is None
        np.testing.assert_array_equal(reader.read(5, 40_000), data[5:40_000])


@pytest.mark.parametrize("bin_us", [1_000, 7_000, 50_000, 1_000_000])
def test_histogram_decoding_runs_of_rows_counts_every_event(
    takes: tuple[Path, Path, EventArray], bin_us: int
) -> None:
    words, columns, rig = takes
    with open_take(words) as w, open_take(columns) as c:
        origin, counts = w.sensor("ev0").histogram(bin_us)
        origin_columns, counts_columns = c.sensor("ev0").histogram(bin_us)
    assert origin == origin_columns
    np.testing.assert_array_equal(counts, counts_columns)
    k = (rig.t - origin) // bin_us
    np.testing.assert_array_equal(counts, np.bincount(k, minlength=counts.size))
