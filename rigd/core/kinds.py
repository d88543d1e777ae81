"""The kinds of rig device, importing nothing (the service's protocol and the lean status path
name them without loading numpy)."""

from __future__ import annotations

from typing import Literal

#: The kinds of device that record data into a take (cameras, event sensors).
SensorKind = Literal["rgb_camera", "event_sensor"]
#: Every kind of rig device: the recording ones and the trigger box.
DeviceKind = Literal[SensorKind, "trigger"]
