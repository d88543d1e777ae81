"""`rigd export --format mcap` read back with the mcap library and rigd's own decoder, and the
bag converted back (`rigd convert`) into a take with the same events, edges, frames and pulses.
The consumers' own code (mcap-ros2-support, rosbags, evt3) runs in bench/ros_acceptance.py."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from rigd.app.cli import app
from rigd.core.timebase import ClockMap
from rigd.evt import StreamDecoder
from rigd.products.ros import msgdefs as m
from rigd.take.reader import open_take

pytest.importorskip("mcap")
pytest.importorskip("rosbags")
runner = CliRunner()
WINDOW_US = 50_000


@pytest.fixture(scope="module")
def exported(ros_take: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("mcap") / "out"
    r = runner.invoke(app, ["export", str(ros_take), "--format", "mcap", "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "(mcap)" in r.output
    (path,) = out.glob("*.mcap")
    return path


def _messages(path: Path) -> dict[str, list[tuple[str, int, Any]]]:
    from mcap.reader import make_reader

    by_topic: dict[str, list[tuple[str, int, Any]]] = defaultdict(list)
    with path.open("rb") as f:
        for schema, channel, msg in make_reader(f).iter_messages(log_time_order=True):
            assert schema is not None
            assert schema.encoding == "ros2msg"
            assert channel.message_encoding == "cdr"
            by_topic[channel.topic].append((schema.name, msg.log_time, m.deserialize(msg.data, schema.name)))
    return by_topic


def _decode_topic(packets: list[Any], clock: Any) -> tuple[np.ndarray, ...]:
    """A topic's events as its clock map message says a consumer gets them (rig us)."""
    restarts = {int(s) for s in clock.restart_seq}
    dec = None
    cmap = ClockMap(int(clock.device_ref_us), int(clock.rig_ref_us), float(clock.rate), float(clock.frac_us))
    xs, ys, ps, ts = [], [], [], []
    for pk in sorted(packets, key=lambda p: int(p.seq)):
        seq = int(pk.seq)
        if dec is None or seq in restarts:
            dec = StreamDecoder(pk.encoding, width=int(pk.width), height=int(pk.height))
        ev = dec.feed(np.asarray(pk.events, np.uint8)).events
        k = int(np.searchsorted(np.asarray(clock.offset_from_seq, np.int64), seq, side="right")) - 1
        t = cmap.to_rig(ev.t + int(np.asarray(clock.offset_us)[k]))
        keep = (t >= clock.window_start_us) & (t < clock.window_end_us)
        xs.append(ev.x[keep]), ys.append(ev.y[keep]), ps.append(ev.p[keep]), ts.append(t[keep])
    return tuple(np.concatenate(a) for a in (xs, ys, ps, ts))


@pytest.mark.slow
def test_every_topic_reads_back_as_the_take(ros_take: Path, exported: Path) -> None:
    topics = _messages(exported)
    with open_take(ros_take) as take:
        meta = json.loads((exported.parent / "export.json").read_text())
        epoch = int(meta["epoch_ns"])
        for name in take.event_sensors:
            ((_, _, clock),) = topics[f"/rigd/{name}/clock_map"]
            packets = [msg for _, _, msg in topics[f"/{name}/events"]]
            assert all(p.encoding == "evt3" and p.time_base == 0 for p in packets)
            x, y, p, t = _decode_topic(packets, clock)
            series = take.sensor(name)
            assert t.size == series.count == clock.events_in_window
            for t0 in range(int(t[0]), int(t[-1]) + 1, WINDOW_US):
                ev = series.events(t0, t0 + WINDOW_US)
                sel = (t >= t0) & (t < t0 + WINDOW_US)
                for a, b in ((x, ev.x), (y, ev.y), (p, ev.p), (t, ev.t)):
                    np.testing.assert_array_equal(a[sel], b)
            edges = [msg for _, _, msg in topics[f"/{name}/triggers"]]
            np.testing.assert_array_equal([e.t_us for e in edges], series.triggers.t)
        for cam in take.cameras:
            fs = take.camera(cam, demosaic=False)
            images = topics[f"/{cam}/image_raw"]
            assert len(images) == len(fs)
            for i, (_, log_ns, img) in enumerate(images):
                assert img.encoding == "bayer_rggb8"
                assert m.stamp_ns(img.header) == log_ns == int(fs.timestamps_us[i]) * 1000 + epoch
                np.testing.assert_array_equal(np.asarray(img.data).reshape(img.height, img.width), fs.raw(i))
            info = topics[f"/{cam}/camera_info"][0][2]
            np.testing.assert_allclose(np.reshape(info.k, (3, 3)), take.calibration[cam]["K"])
            assert info.distortion_model == "plumb_bob"
        pulses = [msg for _, _, msg in topics["/rigd/trigger/pulses"]]
        np.testing.assert_array_equal([p.t_us for p in pulses], take.pulses().t_us)
        ((_, _, tf),) = topics["/tf_static"]
        assert {t.child_frame_id for t in tf.transforms} == set(take.calibration)


@pytest.mark.slow
def test_the_export_directory_is_a_rosbag2_bag(exported: Path) -> None:
    from rosbags.rosbag2 import Reader

    meta = json.loads((exported.parent / "export.json").read_text())
    with Reader(exported.parent) as bag:
        assert bag.message_count == sum(meta["messages"].values())
        assert {c.topic: c.msgcount for c in bag.connections} == meta["messages"]


@pytest.mark.slow
def test_the_export_converts_back_to_the_same_take(ros_take: Path, exported: Path, tmp_path: Path) -> None:
    back = tmp_path / "back.h5"
    r = runner.invoke(app, ["convert", str(exported), str(back)])
    assert r.exit_code == 0, r.output
    with open_take(ros_take) as a, open_take(back) as b:
        assert b.sync_report is not None
        assert not b.sync_report.losses
        assert sorted(a.event_sensors) == sorted(b.event_sensors)
        for name in a.event_sensors:
            ea, eb = a.sensor(name).events(), b.sensor(name).events()
            for k in "xypt":
                np.testing.assert_array_equal(getattr(ea, k), getattr(eb, k))
            np.testing.assert_array_equal(a.sensor(name).triggers.t, b.sensor(name).triggers.t)
        for cam in a.cameras:
            fa, fb = a.camera(cam, demosaic=False), b.camera(cam, demosaic=False)
            assert fb.bayer_pattern == "RGGB"
            np.testing.assert_array_equal(fa.timestamps_us, fb.timestamps_us)
            for i in range(len(fa)):
                np.testing.assert_array_equal(fa.raw(i), fb.raw(i))
        np.testing.assert_array_equal(a.pulses().t_us, b.pulses().t_us)
        ca, cb = a.calibration, b.calibration
        assert ca is not None
        assert cb is not None
        assert sorted(ca) == sorted(cb)
        for dev in ca:
            for k in ("K", "dist", "image_size", "R", "t"):
                np.testing.assert_array_equal(ca[dev][k], cb[dev][k])
        board_a, board_b = a.board_pose, b.board_pose
        assert board_a is not None
        assert board_b is not None
        np.testing.assert_array_equal(board_a[0], board_b[0])


@pytest.mark.slow
def test_the_converted_export_replays_as_the_rig(ros_take: Path, exported: Path, tmp_path: Path) -> None:
    """The take back from the bag plays with `rigd capture --replay`; the replay captures the
    original's events, edges, frames and pulses."""
    from firmware_sim.world import reset_world
    from rigd.app.capture import run_capture
    from rigd.app.replay import replay_config
    from rigd.products.convert import convert

    back = tmp_path / "back.h5"
    convert(exported, back)
    config, duration = replay_config(back, clock="virtual")
    try:
        result = run_capture(config, tmp_path / "replay", duration)
    finally:
        reset_world(f"replay:{back.resolve()}")
    with open_take(ros_take) as a, open_take(result.path) as b:
        for name in a.event_sensors:
            ea, eb = a.sensor(name).events(), b.sensor(name).events()
            for k in "xypt":
                np.testing.assert_array_equal(getattr(ea, k), getattr(eb, k))
            np.testing.assert_array_equal(a.sensor(name).triggers.t, b.sensor(name).triggers.t)
        for cam in a.cameras:
            fa, fb = a.camera(cam, demosaic=False), b.camera(cam, demosaic=False)
            np.testing.assert_array_equal(fa.timestamps_us, fb.timestamps_us)
            np.testing.assert_array_equal(fa.raw(len(fa) - 1), fb.raw(len(fb) - 1))
        np.testing.assert_array_equal(a.pulses().t_us, b.pulses().t_us)


@pytest.mark.slow
def test_slices_png_rig_epoch_and_lz4(ros_take: Path, tmp_path: Path) -> None:
    out = tmp_path / "o"
    args = [
        "export",
        str(ros_take),
        "-f",
        "mcap",
        "-o",
        str(out),
        "--compressed",
        "--ros-epoch",
        "rig",
        "--ros-slice-ms",
        "200",
        "--ros-compression",
        "lz4",
    ]
    r = runner.invoke(app, args)
    assert r.exit_code == 0, r.output
    (path,) = out.glob("*.mcap")
    topics = _messages(path)
    import cv2

    with open_take(ros_take) as take:
        for name in take.event_sensors:
            packets = topics[f"/{name}/events"]
            assert len(packets) <= 3  # 0.34 s of 200 ms slices
            _, _, _, t = _decode_topic([p for _, _, p in packets], topics[f"/rigd/{name}/clock_map"][0][2])
            assert t.size == take.sensor(name).count
        cam = take.cameras[0]
        fs = take.camera(cam, demosaic=False)
        (_, log_ns, first), *_ = topics[f"/{cam}/image_raw/compressed"]
        assert first.format == "png"
        assert log_ns == int(fs.timestamps_us[0]) * 1000
        img = cv2.imdecode(np.asarray(first.data, np.uint8), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(img, fs.raw(0))


def test_bad_slice_is_one_line() -> None:
    r = runner.invoke(app, ["export", "x.h5", "-f", "mcap", "-o", "o", "--ros-slice-ms", "abc"])
    assert r.exit_code == 2
    assert "--ros-slice-ms 'abc'" in r.output


@pytest.mark.slow
def test_words_outside_the_window_are_counted_as_the_take_counted_them(
    ros_take: Path, exported: Path, tmp_path: Path
) -> None:
    import h5py

    back = tmp_path / "back.h5"
    runner.invoke(app, ["convert", str(exported), str(back)])
    with h5py.File(ros_take, "r") as a, h5py.File(back, "r") as b:
        was = json.loads(a.attrs["window_outside_json"])
        now = json.loads(b.attrs["window_outside_json"])
        assert int(b.attrs["window_start_us"]) == int(a.attrs["window_start_us"])
        for name in ("ev0", "ev1"):
            assert now[name] == {k: was[name][k] for k in ("stored_before", "stored_after")}


DATA = Path(__file__).resolve().parents[4].parent / "shared" / "data" / "events"


@pytest.mark.skipif(not DATA.is_dir(), reason=f"shared test data not found at {DATA}")
def test_a_columns_take_exports_as_evt3_slices(tmp_path: Path) -> None:
    """A take stored as x/y/p/t columns (here: `rigd convert` of a RAW file, no cameras, no
    pulses) is encoded to EVT 3.0 per slice and decodes back to its events and edges."""
    from rigd.products.convert import convert

    take_path = tmp_path / "t.h5"
    convert(DATA / "evt3_gen41_sample.raw", take_path)
    out = tmp_path / "o"
    args = [
        "export",
        str(take_path),
        "-f",
        "mcap",
        "-o",
        str(out),
        "--ros-epoch",
        "rig",
        "--ros-slice-ms",
        "1",
    ]
    r = runner.invoke(app, args)
    assert r.exit_code == 0, r.output
    (path,) = out.glob("*.mcap")
    topics = _messages(path)
    assert "/tf_static" not in topics  # no calibration, no transforms
    ((_, _, clock),) = topics["/rigd/ev0/clock_map"]
    packets = [p for _, _, p in topics["/ev0/events"]]
    assert len(packets) == 9  # 8.8 ms of events in 1 ms slices
    x, y, p, t = _decode_topic(packets, clock)
    with open_take(take_path) as take:
        ev = take.sensor("ev0").events()
        for a, b in ((x, ev.x), (y, ev.y), (p, ev.p), (t, ev.t)):
            np.testing.assert_array_equal(a, b)
