"""Device value types shared by the drivers, the take and the config."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from rigd.core.kinds import DeviceKind

#: `DeviceInfo.facts` entry of a device that knows its own calibration exactly (a simulated
#: camera or event sensor): JSON of `GroundTruth`. The capture stores it in the take.
GROUND_TRUTH_FACT = "ground_truth_calibration"


class GroundTruth(BaseModel):
    """A device's exact calibration in its world's frame (OpenCV axes, metres, pixel centres at
    integers): x_cam = R x_world + t, pixels = K x_cam, lens `dist` in OpenCV order.
    The world's frame is the scene's board plane (z = 0, x right, y down)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    world: str = Field(description="The world the pose is in (devices of one world share it).")
    K: list[list[float]]
    dist: list[float]
    image_size: tuple[int, int]
    R: list[list[float]]
    t: list[float]

    @classmethod
    def of(cls, info: DeviceInfo) -> GroundTruth | None:
        """The truth a device's facts carry, or None; a malformed entry is a ValueError."""
        raw = info.facts.get(GROUND_TRUTH_FACT)
        return None if raw is None else cls.model_validate_json(raw)


class DeviceInfo(BaseModel):
    """Identity of an opened device, written into every take."""

    model_config = ConfigDict(frozen=True)

    kind: DeviceKind
    spec: str = Field(description="The spec the device was opened from.")
    vendor: str = ""
    model: str = ""
    serial: str = ""
    firmware: str = ""
    facts: dict[str, str] = Field(
        default_factory=dict,
        description="Backend facts worth keeping with the data (stream format, sensor generation, ...).",
    )


@dataclass(frozen=True, slots=True)
class PulseBatch:
    """Pulses the trigger source reported: index from 0 at START, time in its clock."""

    index: NDArray[np.int64]
    t_us: NDArray[np.int64]
    host_time_ns: NDArray[np.int64]

    @classmethod
    def empty(cls) -> PulseBatch:
        return cls(np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, np.int64))

    def __len__(self) -> int:
        return int(self.index.shape[0])
