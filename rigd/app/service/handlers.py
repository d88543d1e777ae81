"""The daemon's request handlers: one method per protocol command.

The daemon (`rigd.app.service.daemon`) owns the sockets, the worker threads and the dispatch;
what a command does lives here, on the rig's slot (`rigd.app.service.rig_slot`: who has the rig)
and the daemon's telemetry. A command that takes seconds to minutes (opening devices,
enumerating cameras, sealing big takes) is split by `claim`: what must be decided before the
next request is answered (who owns the rig) runs at once, the rest is a job for a worker.
"""

from __future__ import annotations

import functools
import os
import threading
from collections.abc import Callable
from typing import Any

from pydantic import BaseModel

from rigd import __version__
from rigd.app.config import RigConfig
from rigd.app.service.protocol import (
    PROTOCOL_VERSION,
    CaptureArgs,
    CapturePartArgs,
    PulsesArgs,
    ShutdownArgs,
    StopArgs,
    TakeReadArgs,
    TakeStatArgs,
    Telemetry,
)
from rigd.app.service.requests import RequestError
from rigd.app.service.rig_slot import RigSlot
from rigd.app.service.take_files import TakeHashes, read_take


class Handlers:
    """Answers the control requests; `run(cmd, args)` for a quick one, `claim` for a slow one."""

    def __init__(
        self,
        config: RigConfig,
        slot: RigSlot,
        *,
        telemetry: Callable[[], Telemetry],
        stop: threading.Event,
    ) -> None:
        self._config = config
        self._slot = slot
        self._telemetry = telemetry
        self._stop = stop
        self._hashes = TakeHashes()

    def run(self, cmd: str, args: BaseModel) -> dict[str, Any]:
        """Answer `cmd` (validated against the protocol: its handler exists, `args` is its model)."""
        handler: Callable[[Any], dict[str, Any]] = getattr(self, f"cmd_{cmd}")
        return handler(args)

    def claim(self, cmd: str, args: BaseModel) -> Callable[[], dict[str, Any]]:
        """For a slow command: decide now who owns the rig (`busy` at once if it cannot have
        it), and return the rest as a job for a worker thread."""
        claim: Callable[[Any], Callable[[], dict[str, Any]]] | None = getattr(self, f"claim_{cmd}", None)
        if claim is None:
            return functools.partial(self.run, cmd, args)
        return claim(args)

    def claim_capture(self, args: CaptureArgs) -> Callable[[], dict[str, Any]]:
        session = self._slot.begin_capture(args)
        return functools.partial(self._slot.start_capture, session, args)

    def claim_capture_part(self, args: CapturePartArgs) -> Callable[[], dict[str, Any]]:
        session = self._slot.begin_part(args)
        return functools.partial(self._slot.start_capture, session, args)

    def claim_recover(self, _: BaseModel) -> Callable[[], dict[str, Any]]:
        return self._slot.claim_recovery()

    # -- the commands ------------------------------------------------------------------
    def cmd_ping(self, _: BaseModel) -> dict[str, Any]:
        return {
            "rigd": __version__,
            "protocol": PROTOCOL_VERSION,
            "pid": os.getpid(),
            "state": self._slot.state,
        }

    def cmd_status(self, _: BaseModel) -> dict[str, Any]:
        return self._telemetry().model_dump(mode="json")

    def cmd_config(self, _: BaseModel) -> dict[str, Any]:
        return self._config.model_dump(mode="json")

    def cmd_capture(self, args: CaptureArgs) -> dict[str, Any]:
        return self.claim_capture(args)()

    def cmd_capture_part(self, args: CapturePartArgs) -> dict[str, Any]:
        return self.claim_capture_part(args)()

    def cmd_pulses(self, args: PulsesArgs) -> dict[str, Any]:
        return self._slot.pulses(args)

    def cmd_stop(self, args: StopArgs) -> dict[str, Any]:
        return self._slot.stop(args.reason)

    def cmd_devices(self, _: BaseModel) -> dict[str, Any]:
        from drivers.discovery import discover

        return discover().to_dict()

    def cmd_recover(self, args: BaseModel) -> dict[str, Any]:
        return self.claim_recover(args)()

    def cmd_take_read(self, args: TakeReadArgs) -> dict[str, Any]:
        """Bytes of one of this daemon's take files (a multi-host take's part, gathered)."""
        return read_take(self._config.service.take_dir, args.file, args.offset, args.length, args.binary)

    def cmd_take_stat(self, args: TakeStatArgs) -> dict[str, Any]:
        """Size and sha256 of one of this daemon's take files (the sha256 is null while it is
        being computed, in the background: ask again)."""
        return self._hashes.stat(self._config.service.take_dir, args.file)

    def cmd_shutdown(self, args: ShutdownArgs) -> dict[str, Any]:
        if self._slot.running() and not args.force:
            raise RequestError(
                "busy", "a take is running; stop it first or pass force=true (it is finalized)"
            )
        self._stop.set()
        return {"shutting_down": True}
