"""`replay:///abs/TAKE.h5?device=NAME`: a recorded take played back as a rig, through the real drivers.

Every device of a recorded take can be opened again from the file: the trigger box runs the
simulated firmware on a pty (the host opens it with pyserial) and reports the recorded pulse
times; a camera delivers the recorded frames with their device timestamps and counters; an
event sensor encodes the recorded events and trigger-in edges, back in its own clock, into an
EVT 3.0 byte stream that the production decoder reads. The devices share one `SimWorld`
per take (and clock: `clock=virtual` replays as fast as the host reads, real time otherwise),
so a re-captured replay holds the same frames and events and ties the same clocks.

Times: the take holds rig times (trigger-box microseconds). When the box is STARTed it puts
the recorded pulse 0 one start lead ahead and fixes `rig = true + shift` for the world; every
device waits for that shift and hands out its data when true time reaches it. Device times come
back exactly: camera exposure starts and trigger-in edges are stored in device time, and an
event's device time is the integer whose rig time (through the take's own clock map) is the
recorded one.

Fault switches as on `sim://` devices (docs/sim-faults.md): box `drop_pulses`, `garbage_every`,
`silent_after`, `garbage_after`; camera `drop_frames`; camera and event sensor `unplug_at_s` /
`unplug_for_s`, and `clock_reset=1` (a device opened after its replug counts from 0).

Here: the trigger box. The recording and its timing are in `replay_recording`, the devices in
`replay_camera` and `replay_event_sensor`.
"""

from __future__ import annotations

from drivers.registry import DeviceSpec
from drivers.serial_trigger import SerialTrigger
from firmware_sim.box_devices import open_box_trigger
from firmware_sim.replay_recording import Recording, Timeline, replay_world
from firmware_sim.spec_params import ReplayTriggerParams, check_params
from firmware_sim.trigger_box import START_LEAD_US, SimTriggerBox
from firmware_sim.world import DeviceClock


class ReplayTriggerBox(SimTriggerBox):
    """The sim firmware, reporting the recorded pulse times instead of a computed schedule."""

    def _first_pulse_time(self) -> int:
        rec = self.world.resource("replay_recording", lambda: None)
        timeline = self.world.resource("replay_timeline", Timeline)
        assert isinstance(rec, Recording)
        assert isinstance(timeline, Timeline)
        t0 = rec.pulse_time(int(rec.pulse_index[0]))
        assert t0 is not None
        # The box clock is rig time: pulse 0 one start lead from now.
        self.clock = DeviceClock(t0 - (self.world.now_us() + START_LEAD_US), 0.0)
        self.world.register_clock("trigger", self.clock)
        timeline.set(self.clock.offset_us)
        self._recording = rec
        return t0

    def _pulse_box_time(self, t0: int, rate_hz: float, k: int) -> int | None:
        return self._recording.pulse_time(k + int(self._recording.pulse_index[0]))


def open_replay_trigger(spec: DeviceSpec) -> SerialTrigger:
    """Factory for `replay:///abs/take.h5?device=trigger` (+ the box's fault switches)."""
    check_params(spec, ReplayTriggerParams, "replayed trigger box")
    world, _, _ = replay_world(spec)
    return open_box_trigger(spec, world, ReplayTriggerBox)
