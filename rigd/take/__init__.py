"""Take files: writing (capture pipeline), reading (training jobs), validation and recovery."""

from rigd.core.errors import TakeInUseError, TakeTruncatedError
from rigd.take.event_series import EventSeries
from rigd.take.frame_series import FrameSeries
from rigd.take.h5file import compression_options
from rigd.take.reader import (
    CameraSummary,
    EventSensorSummary,
    Take,
    TakeSummary,
    open_take,
)
from rigd.take.recover import RecoveryReport, recover_take
from rigd.take.recover_dir import find_unfinished
from rigd.take.repair import Trim, check_repair
from rigd.take.sinks import DeviceWriteStats
from rigd.take.validate import validate_take
from rigd.take.writer import TakeWriter

__all__ = [
    "CameraSummary",
    "DeviceWriteStats",
    "EventSensorSummary",
    "EventSeries",
    "FrameSeries",
    "RecoveryReport",
    "Take",
    "TakeInUseError",
    "TakeSummary",
    "TakeTruncatedError",
    "TakeWriter",
    "Trim",
    "check_repair",
    "compression_options",
    "find_unfinished",
    "open_take",
    "recover_take",
    "validate_take",
]
