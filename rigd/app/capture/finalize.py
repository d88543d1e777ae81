"""The end of a take: fit every device clock to the pulses, say why it ended, seal the file."""

from __future__ import annotations

import json
import logging

from drivers.base import Capability, RgbCamera
from rigd.app.capture.channel import DeviceChannel, TriggerChannel
from rigd.app.capture.control import RunControl
from rigd.app.capture.faults import FaultBoard
from rigd.app.capture.ledger import LossLedger
from rigd.app.config import RigConfig
from rigd.core.schema import SyncReport
from rigd.core.settings import CameraSettings
from rigd.sync import DeviceObservations, synchronize
from rigd.take.writer import TakeWriter

log = logging.getLogger(__name__)


def software_synced(channel: DeviceChannel) -> bool:
    """A camera whose frames are matched to pulses by host time: it has no trigger input, or
    it was told to run free."""
    if not isinstance(channel.device, RgbCamera):
        return False
    hardware = Capability.HARDWARE_TRIGGER in channel.device.capabilities
    return not hardware or (
        isinstance(channel.settings, CameraSettings) and channel.settings.trigger_mode != "hardware"
    )


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
    channels: dict[str, DeviceChannel],
    ledger: LossLedger,
    faults: FaultBoard,
    control: RunControl,
    emitted: int,
) -> tuple[SyncReport, str]:
    """Fit, report and seal; returns the sync report and why the take ended."""
    pulses = trigger.pulses(emitted)
    observations = []
    for name, ch in channels.items():
        t, host, counter = ch.obs.arrays()
        anchors = None if ch.anchors is None else ch.anchors.arrays()
        observations.append(
            DeviceObservations(name, ch.kind, t, host, counter if ch.kind == "rgb_camera" else None, anchors)
        )
    slaves = {
        s.name: s.settings.sync_master
        for s in config.event_sensors
        if s.settings.sync_mode == "slave" and s.settings.sync_master is not None
    }
    software = {name for name, ch in channels.items() if software_synced(ch)}
    result = synchronize(
        pulses,
        observations,
        config.trigger.settings.rate_hz,
        ledger.records(),
        shares_clock_with=slaves,
        software_synced=software,
    )
    report = result.report
    report.device_counters = ledger.counters()
    for name, why in ledger.written_off().items():
        report.warnings.append(f"{name} failed mid-take and was written off: {why}")
    report.warnings.extend(
        [*faults.history(), *(f"{line} (still active at the end)" for line in faults.active_lines())]
    )
    if control.stop_by_fault:
        report.warnings.append(f"the rig stopped the take itself: {control.stop_reason}")
    reason = end_reason(control, emitted)
    writer.set_end_reason(reason)
    report.trigger_link = trigger.device.link_stats()
    cameras = [name for name, ch in channels.items() if ch.kind == "rgb_camera"]
    frame_index = {name: result.observation_pulse_index[name] for name in cameras}
    writer.finalize(result.maps, frame_index, report)
    log.info(
        "take %s finalized: %s",
        writer.path,
        json.dumps({name: ch.written for name, ch in channels.items() if ch.kind == "rgb_camera"}),
    )
    return report, reason
