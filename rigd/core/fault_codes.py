"""The codes of the faults a capture posts (its fault board) and the daemon reports (telemetry,
`rigd status`, the console, metrics): one list, so a fault raised on the capture path can never
be one the protocol refuses to carry."""

from __future__ import annotations

from typing import Literal, get_args

FaultCode = Literal[
    "trigger_silent",
    "trigger_garbage",
    "device_failed",
    "device_reconnecting",
    "disk_low",
    "disk_full",
    "queue_full",
    "writer_failed",
    "writer_stalled",
    "overload",
]
FAULT_CODES: tuple[str, ...] = get_args(FaultCode)
