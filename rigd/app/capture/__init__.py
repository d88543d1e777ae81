"""The capture path: devices -> channels -> one bounded queue -> the writer -> a sealed take.

Modules, in the order data flows through them:
- `channel`: one per device (read, reconnect, re-tie a restarted clock via `clock_reset`);
- `items`: the typed items on the writer queue, and the queue;
- `writer_loop`: the writer thread (the only one touching the take file while it runs);
- `ledger`: every loss, and the journal flushed into the take;
- `faults`: the fault board and the trigger / disk / flush watchdogs;
- `preflight`: the rig's devices can do what the config asks;
- `finalize`: fit every device clock, say why the take ended, seal it;
- `request`: what a take is asked for (length, directory, file name), checked up front;
- `session`: `CaptureSession`, which wires the rest together; `run`: `run_capture`, blocking;
- `results`, `live`, `control`, `ballast`: what is reported, live counters, stopping, disk ballast.
"""

from rigd.app.capture.ballast import Ballast, remove_stale_ballast
from rigd.app.capture.channel import pulse_log
from rigd.app.capture.faults import FLUSH_STALL_SLACK_S
from rigd.app.capture.request import new_take_path
from rigd.app.capture.results import (
    ActiveFault,
    CaptureResult,
    DeviceSnapshot,
    DeviceState,
    Progress,
    SessionSnapshot,
    SessionState,
)
from rigd.app.capture.run import run_capture
from rigd.app.capture.session import CaptureSession

__all__ = [
    "FLUSH_STALL_SLACK_S",
    "ActiveFault",
    "Ballast",
    "CaptureResult",
    "CaptureSession",
    "DeviceSnapshot",
    "DeviceState",
    "Progress",
    "SessionSnapshot",
    "SessionState",
    "new_take_path",
    "pulse_log",
    "remove_stale_ballast",
    "run_capture",
]
