"""Take files: writing (capture pipeline), reading (training jobs) and validation."""

from rigd.take.reader import (
    CameraSummary,
    EventSensorSummary,
    FrameSeries,
    Take,
    TakeSummary,
    open_take,
)
from rigd.take.validate import validate_take
from rigd.take.writer import DeviceWriteStats, TakeWriter, compression_options

__all__ = [
    "CameraSummary",
    "DeviceWriteStats",
    "EventSensorSummary",
    "FrameSeries",
    "Take",
    "TakeSummary",
    "TakeWriter",
    "compression_options",
    "open_take",
    "validate_take",
]
