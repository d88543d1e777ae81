"""Device value types shared by the drivers, the take and the config."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

DeviceKind = Literal["rgb_camera", "event_sensor", "trigger"]


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
