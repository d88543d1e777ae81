"""`rigd convert BAG TAKE.h5` on bags made with rosbags' own writer the way metavision_driver
records: packets of a RAW file's EVT words; missing, out-of-order and undecodable packets
become loss records; `mono` packets unpack as event_camera_codecs defines them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from rigd.app.cli import app
from rigd.evt import read_raw
from rigd.products.convert import convert
from rigd.products.ros.bag_convert import BagConvertError, sensor_name
from rigd.take.reader import open_take
from tests.rigd.products.ros.conftest import packet, raw_packets, write_bag

pytest.importorskip("rosbags")
DATA = Path(__file__).resolve().parents[4].parent / "shared" / "data" / "events"
runner = CliRunner()
TOPIC = "/event_camera/events"


def test_sensor_names_from_topics() -> None:
    assert sensor_name("/event_camera/events") == "event_camera"
    assert sensor_name("/cam_0/image_raw") == "cam_0"
    assert sensor_name("/a/b/events") == "a_b"


@pytest.mark.skipif(not DATA.is_dir(), reason=f"shared test data not found at {DATA}")
@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
@pytest.mark.parametrize("name", ["evt3_gen41_sample.raw", "evt2_gen3_sample.raw"])
def test_driver_bag_converts_to_the_recordings_events(tmp_path: Path, name: str, storage: str) -> None:
    fmt, w, h, chunks = raw_packets(DATA / name)
    bag = write_bag(
        tmp_path / "bag",
        TOPIC,
        ((1_000_000 * (i + 1), packet(i, c, encoding=fmt, width=w, height=h)) for i, c in enumerate(chunks)),
        storage=storage,
    )
    take_path = tmp_path / "t.h5"
    r = runner.invoke(app, ["convert", str(bag), str(take_path)])
    assert r.exit_code == 0, r.output
    ref = read_raw(DATA / name)[1]
    with open_take(take_path) as take:
        assert take.event_sensors == ["event_camera"]
        ev = take.sensor("event_camera").events()
        assert len(ev) == len(ref.events)
        for k in "xypt":
            np.testing.assert_array_equal(getattr(ev, k), getattr(ref.events, k))
        np.testing.assert_array_equal(take.sensor("event_camera").triggers.t, ref.triggers.t)
        assert take.sync_report is not None
        assert not take.sync_report.losses
        assert "not tied" in " ".join(take.sync_report.warnings)


@pytest.mark.skipif(not DATA.is_dir(), reason=f"shared test data not found at {DATA}")
def test_missing_out_of_order_and_bad_packets_are_loss_records(tmp_path: Path) -> None:
    fmt, w, h, chunks = raw_packets(DATA / "evt3_gen41_sample.raw")
    seqs = list(range(len(chunks)))
    payloads = []
    for i in seqs:
        if i in (5, 6):  # two packets lost on the way
            continue
        enc = "evt4" if i == 9 else fmt  # an encoding nobody decodes
        payloads.append((1000 * (i + 1), packet(i, chunks[i], encoding=enc, width=w, height=h)))
    payloads.insert(12, (1000 * 13, packet(3, chunks[3], encoding=fmt, width=w, height=h)))  # a late repeat
    payloads.append((10**9, b"\x00\x01\x00\x00garbage"))  # not an EventPacket at all
    bag = write_bag(tmp_path / "bag", TOPIC, payloads)
    take_path = tmp_path / "t.h5"
    convert(bag, take_path)
    with open_take(take_path) as take:
        report = take.sync_report
        assert report is not None
        reasons = " | ".join(rec.reason for rec in report.losses)
        assert "2 EventPacket(s) missing" in reasons
        assert "1 EventPacket(s) out of order" in reasons
        assert "1 EventPacket(s) on event_camera's topic could not be decoded: seq 9: evt4" in reasons
        assert "1 message(s) on /event_camera/events are not event_camera_msgs/msg/EventPacket CDR" in reasons
        assert sum(rec.count for rec in report.losses) >= 5  # and what the decoder skipped after the gap
        assert take.sensor("event_camera").count > 0


def test_mono_packets_unpack_as_event_camera_codecs(tmp_path: Path) -> None:
    t = np.array([5, 9, 400], np.uint64)
    x, y, p = np.array([1, 2, 3], np.uint64), np.array([4, 5, 6], np.uint64), np.array([1, 0, 1], np.uint64)
    words = (p << np.uint64(63)) | (y << np.uint64(48)) | (x << np.uint64(32)) | (t * np.uint64(1000))
    base = 7_000_000_000
    data = words.astype("<u8").tobytes()
    bag = write_bag(
        tmp_path / "bag", TOPIC, [(base, packet(0, data, encoding="mono", width=8, height=8, time_base=base))]
    )
    convert(bag, tmp_path / "t.h5")
    with open_take(tmp_path / "t.h5") as take:
        ev = take.sensor("event_camera").events()
        np.testing.assert_array_equal(ev.t, (base + t.astype(np.int64) * 1000) // 1000)
        np.testing.assert_array_equal(ev.x, x)
        np.testing.assert_array_equal(ev.p, np.where(p > 0, 1, -1))


def test_bag_without_event_or_image_topics_is_refused(tmp_path: Path) -> None:
    from rosbags.rosbag2 import Writer

    from rigd.products.ros import msgdefs as m

    with Writer(tmp_path / "bag", version=9) as w:
        conn = w.add_connection("/rigd/trigger/pulses", m.TRIGGER_PULSE, typestore=m.typestore())
        w.write(
            conn,
            1,
            m.serialize(
                m.new(m.TRIGGER_PULSE, header=m.header(1, "rig"), index=0, t_us=0, host_time_ns=0),
                m.TRIGGER_PULSE,
            ),
        )
    with pytest.raises(BagConvertError, match="no event_camera_msgs/EventPacket or sensor_msgs/Image topic"):
        convert(tmp_path / "bag", tmp_path / "t.h5")
    assert not (tmp_path / "t.h5").exists()
