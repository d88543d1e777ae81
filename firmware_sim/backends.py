"""Entry points of the `sim://` and `replay://` backends (see `[project.entry-points."rigd.backends"]`)."""

from firmware_sim.box_devices import open_sim_trigger
from firmware_sim.event_sensor import open_sim_event_sensor
from firmware_sim.replay import open_replay_trigger
from firmware_sim.replay_camera import open_replay_camera
from firmware_sim.replay_event_sensor import open_replay_event_sensor
from firmware_sim.rgb_camera import open_sim_camera

__all__ = [
    "open_replay_camera",
    "open_replay_event_sensor",
    "open_replay_trigger",
    "open_sim_camera",
    "open_sim_event_sensor",
    "open_sim_trigger",
]
