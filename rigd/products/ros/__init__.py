"""rigd in the ROS 2 world: takes out as MCAP (`rigd export --format mcap`), rosbag2 recordings
in as takes (`rigd convert BAG TAKE.h5`).

The message definitions travel with the project as `.msg` texts under `msg/` (no ROS install);
`rigd.products.ros.msgdefs` registers them with a `rosbags` type store, which serializes and
deserializes CDR. See docs/export.md ("mcap") for the topics and the timestamp rule.
"""
