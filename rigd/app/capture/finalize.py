"""The end of a take: fit every device clock to the pulses, say why it ended, seal the file."""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from typing import Any

from rigd.app.capture.channel import DeviceChannel, TriggerChannel
from rigd.app.capture.control import RunControl
from rigd.app.capture.faults import FaultBoard
from rigd.app.capture.ledger import LossLedger
from rigd.app.config import RigConfig
from rigd.core.schema import SyncReport
from rigd.take.seal import Bookkeeping, Seal, TakeEnd, fit_take, seal_take
from rigd.take.writer import TakeWriter

log = logging.getLogger(__name__)


def end_reason(control: RunControl, emitted: int) -> str:
    if control.stop_by_fault:
        return f"stopped by the rig: {control.stop_reason}"
    if control.stop_reason is not None:
        return f"stopped: {control.stop_reason}"
    return f"all {emitted} pulses done"


def finalize_take(
    config: RigConfig,
    writer: TakeWriter,
    trigger: TriggerChannel,
    channels: Mapping[str, DeviceChannel[Any, Any]],
    ledger: LossLedger,
    faults: FaultBoard,
    control: RunControl,
    emitted: int,
    window: tuple[int | None, int | None, int, Mapping[str, Mapping[str, int]]],
) -> tuple[SyncReport, str]:
    """Fit, report and seal with what the capture holds in memory (`rigd.take.seal`, the same
    steps `rigd recover` seals a crashed take with); returns the sync report and why the take
    ended. `window`: the trigger window and what arrived outside it."""
    observations = [
        ch.stream.sync_observations(None if (anchors := ch.reading.anchors) is None else anchors.arrays())
        for ch in channels.values()
    ]
    end = TakeEnd(
        trigger.pulses(emitted),
        observations,
        config.trigger.settings.rate_hz,
        ledger.records(),
        [cam.name for cam in config.cameras],
        shares_clock_with={
            s.name: s.settings.sync_master
            for s in config.event_sensors
            if s.settings.sync_mode == "slave" and s.settings.sync_master is not None
        },
        software_synced={name for name, ch in channels.items() if ch.software_synced()},
    )
    result = fit_take(end)
    book = Bookkeeping(
        device_counters=ledger.counters(),
        trigger_link=trigger.device.link_stats(),
        written_off=ledger.written_off(),
        fault_history=faults.history(),
        faults_active=faults.active_lines(),
    )
    notes = [f"the rig stopped the take itself: {control.stop_reason}"] if control.stop_by_fault else []
    seal = Seal.fitted(end, result, book, active_until="the end", notes=notes)
    reason = end_reason(control, emitted)
    seal_take(writer, seal, window=window, end_reason=reason)
    log.info(
        "take %s finalized: %s",
        writer.path,
        json.dumps({cam.name: channels[cam.name].stream.written for cam in config.cameras}),
    )
    return result.report, reason
