"""The shipped .msg texts against the definitions rosbags carries for ROS 2 Humble: the same
fields, types and order (so a bag rigd writes reads wherever ROS reads it)."""

from __future__ import annotations

import pytest

from rigd.products.ros import msgdefs as m

pytest.importorskip("rosbags")

STANDARD = [
    m.IMAGE,
    m.COMPRESSED_IMAGE,
    m.CAMERA_INFO,
    m.TF_MESSAGE,
    "std_msgs/msg/Header",
    "geometry_msgs/msg/TransformStamped",
    "geometry_msgs/msg/Transform",
    "geometry_msgs/msg/Quaternion",
    "geometry_msgs/msg/Vector3",
    "sensor_msgs/msg/RegionOfInterest",
]


@pytest.mark.parametrize("typename", STANDARD)
def test_shipped_definition_has_the_fields_of_ros2(typename: str) -> None:
    from rosbags.typesys import Stores, get_typestore

    ros = get_typestore(Stores.ROS2_HUMBLE)
    assert m.typestore().fielddefs[typename] == ros.fielddefs[typename]


def test_event_packet_fields_are_event_camera_msgs() -> None:
    fields = [name for name, _ in m.typestore().fielddefs[m.EVENT_PACKET][1]]
    assert fields == ["header", "height", "width", "seq", "time_base", "encoding", "is_bigendian", "events"]


def test_schema_text_lists_every_dependency_once() -> None:
    text = m.schema_text(m.CAMERA_INFO)
    assert text.startswith("# This message defines meta information for a camera.")
    deps = [ln[5:] for ln in text.splitlines() if ln.startswith("MSG: ")]
    assert deps == ["std_msgs/Header", "builtin_interfaces/Time", "sensor_msgs/RegionOfInterest"]


def test_stamp_round_trip_before_and_after_the_epoch() -> None:
    for ns in (0, 1, 1_795_923_132_000_964_000, -1_500):
        assert m.stamp_ns(m.header(ns, "x")) == ns


def test_camera_info_models_and_refusal() -> None:
    import numpy as np

    from rigd.core.errors import TakeError
    from rigd.products.ros.streams import TakeStreams

    streams = TakeStreams.__new__(TakeStreams)
    kmat = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    for dist, model, n in (
        (np.zeros(5), "plumb_bob", 5),
        (np.arange(8) * 0.01, "rational_polynomial", 8),
        (np.r_[np.arange(8) * 0.01, np.zeros(6)], "rational_polynomial", 8),
    ):
        streams.calib = {"cam0": {"K": kmat, "dist": dist}}
        info = streams.camera_info("cam0", 5, (480, 640))
        assert info.distortion_model == model
        assert len(info.d) == n
        np.testing.assert_array_equal(np.reshape(info.p, (3, 4))[:, :3], kmat)
    streams.calib = {"cam0": {"K": kmat, "dist": np.r_[np.zeros(8), 0.1, np.zeros(5)]}}
    with pytest.raises(TakeError, match="14 distortion coefficients"):
        streams.camera_info("cam0", 5, (480, 640))
