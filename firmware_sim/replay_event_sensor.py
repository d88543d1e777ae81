"""A recorded event sensor played back (`replay:///abs/TAKE.h5?device=EV`): the recorded events and
trigger-in edges, back in the sensor's own clock, encoded into the EVT 3.0 byte stream that the
production decoder reads.
"""

from __future__ import annotations

import logging
import math
import threading

import numpy as np

from drivers.base import Capability
from drivers.evt_stream import DecodingEventSensor
from drivers.lifecycle import END, Signal
from drivers.registry import DeviceSpec
from firmware_sim.clock import Hold
from firmware_sim.event_sensor import SLICE_US, _Packet
from firmware_sim.replay_recording import (
    VIRTUAL_LEAD,
    Recording,
    Timeline,
    buffers_param,
    clock_reset_param,
    device_name,
    replay_world,
    reset_base,
    rig_to_device,
)
from firmware_sim.spec_params import ReplaySensorParams, check_params
from firmware_sim.world import SimWorld, Unpluggable, UnplugParams, unplug_params, wait_for_room
from rigd.core.devices import DeviceInfo
from rigd.core.events import EventArray, TriggerEvents
from rigd.evt import Evt3Encoder
from rigd.take import Take

log = logging.getLogger(__name__)

#: Events read from the take at a time by a replayed sensor (whole LZ4 chunks, once each).
_READ_AHEAD = 1 << 20


class ReplayEventSensor(Unpluggable, DecodingEventSensor[_Packet]):
    """A recorded event sensor: every `SLICE_US` of true time, the recorded events and trigger
    edges of that span, back in the sensor clock, as one EVT 3.0 buffer that the host decodes.
    A buffer the full queue gives up is counted as `packets_dropped`, its events in
    `device_dropped` and its trigger edges in `triggers_dropped` (as the sim sensor counts)."""

    _device_label = "event sensor"
    _capabilities = frozenset({Capability.TRIGGER_IN, Capability.DEVICE_TIMESTAMPS, Capability.CLOCK_SYNC})
    _overflow_name = "packets_dropped"
    _overflow_is_loss = False  # counted in events, by `_deliver`

    def __init__(
        self,
        spec: DeviceSpec,
        world: SimWorld,
        rec: Recording,
        timeline: Timeline,
        *,
        buffer_packets: int,
        unplug: UnplugParams | None,
        clock_reset: bool = False,
    ) -> None:
        name = device_name(spec)
        self._track = rec.sensor(name)
        self._clock_reset, self._base = clock_reset, 0
        geometry = (self._track.width, self._track.height)
        super().__init__("evt3", geometry, buffers=buffer_packets, merge=64, drain_on_stop=True)
        self._world, self._name, self._rec, self._timeline = world, name, rec, timeline
        self._unplug = unplug
        self._info = DeviceInfo(
            kind="event_sensor",
            spec=spec.raw,
            vendor="rigd-replay",
            model="ReplayEventSensor",
            serial=f"{rec.path.name}/{name}",
            firmware="replay-1",
            facts={"evt_format": "evt3"},
        )
        self._plug_in(world, name, spec.raw)
        self._lock = threading.Lock()
        self._encoder = Evt3Encoder()
        self._take: Take | None = None
        self._buf = EventArray.empty()
        """Events read ahead (rig time), from `_pos` in the file: slices are cut from it, so a
        5 ms slice does not decompress whole chunks again."""
        self._pos = 0
        self._t_prev: float | None = None
        self._final = False
        self._hold: Hold | None = None
        self._counts = {
            "events": 0,
            "triggers": 0,
            "bytes": 0,
            "inexact_times": 0,
            "packets_lost_unplugged": 0,
            "triggers_dropped": 0,
        }
        self._events_lost = 0
        """Events of the buffers the full queue gave up (real time: the reader fell behind)."""
        self._unlisten = self._fault.listen(self._on_unplug)

    def warm_up(self) -> None:
        """Compile the EVT 3.0 encoder a slice runs, on a throwaway encoder and a tiny sample."""
        one = np.zeros(1, np.uint16)
        events = EventArray(one, one.copy(), np.ones(1, np.int8), np.ones(1, np.int64))
        Evt3Encoder().encode(
            events, TriggerEvents(np.zeros(1, np.int64), np.ones(1, np.uint8), np.zeros(1, np.uint8))
        )
        super().warm_up()

    def _do_start(self) -> None:
        if self._take is None:
            self._take = Take(self._rec.path)
        shift = self._timeline.wait(0.0)
        now = self._world.now_us()
        self._t_prev = None if shift is None else now
        self._buf = EventArray.empty()
        self._pos = 0 if shift is None else self._take.sensor(self._name).index(math.ceil(now + shift))
        self._base = reset_base(self._clock_reset, self._world, self._name, self._track.cmap, shift, now)
        self._final = False
        self._hold = self._world.hold() if self._world.virtual else None
        self._arm_unplug(self._unplug, self._world.now_us(), lost_frames_on_edges=False)

    def _do_close(self) -> None:
        self._unlisten()
        if self._hold is not None:
            self._hold.release()
        if self._take is not None:
            self._take.close()
            self._take = None
        super()._do_close()

    def _join(self, parts: list[_Packet]) -> tuple[bytes, int]:
        with self._lock:
            if self._dead(self._world.now_us()):
                self._note_unplug_locked(parts)
                raise self._unplugged_error()
        return super()._join(parts)

    def _counters(self) -> tuple[int, dict[str, int]]:
        with self._lock:
            counts, lost = dict(self._counts), self._events_lost
        _, decoder = super()._counters()
        return lost, {**counts, **decoder}

    def _deliver(self, item: _Packet) -> bool:
        """Into the queue; a full one gives up a buffer: its events and edges are counted."""
        lost = self._queue.put(item)
        if lost is None:
            return True
        with self._lock:
            self._events_lost += lost.n_events
            self._counts["triggers_dropped"] += lost.n_triggers
        log.warning(
            "replay event sensor %s: reader behind, queue full: dropped a buffer of %d events, %d triggers",
            self._name,
            lost.n_events,
            lost.n_triggers,
        )
        return False

    def _note_unplug_locked(self, lost: list[_Packet]) -> None:
        lost = [*lost, *self._queue.drain()]
        self._counts["packets_lost_unplugged"] += len(lost)
        if not self._unplug_noted:
            self._unplug_noted = True
            log.warning("replay event sensor %s unplugged", self._name)

    def _grab(self, timeout_s: float) -> _Packet | Signal | None:
        if self._final:
            if self._hold is not None:
                self._hold.release()
            return END
        shift = self._timeline.wait(timeout_s)
        if shift is None:
            return None
        if self._t_prev is None:  # the first slice reaches back to the start of the recording
            self._t_prev = -math.inf
            t_end = self._world.now_us()
        else:
            start = self._t_prev if math.isfinite(self._t_prev) else self._world.now_us()
            wake = start + SLICE_US
            stop = self._stop_asked
            awake = self._hold.sleep_until(wake, stop) if self._hold else self._world.sleep_until(wake, stop)
            now = self._world.now_us()
            if awake:
                t_end = start + SLICE_US * max(1, math.floor((now - start) / SLICE_US))
            else:
                t_end, self._final = now, True
        if self._dead(self._world.now_us()):
            with self._lock:
                self._note_unplug_locked([])
            if self._hold is not None:
                self._hold.release()  # a dead device no longer holds the world's time
            return END
        packet = self._slice(self._t_prev, t_end, shift)
        self._t_prev = t_end
        if packet is not None and self._hold is not None:
            wait_for_room(self._queue, VIRTUAL_LEAD, self._stop_asked.is_set)
        return packet

    def _take_until(self, hi_rig: int) -> EventArray:
        """The recorded events before rig time `hi_rig` not handed out yet, read ahead in blocks."""
        assert self._take is not None
        n = self._track.n_events
        while self._pos < n and (len(self._buf) == 0 or int(self._buf.t[-1]) < hi_rig):
            stop = min(self._pos + _READ_AHEAD, n)
            block = self._take.sensor(self._name).by_index(self._pos, stop)
            self._buf = EventArray.concatenate([self._buf, block])
            self._pos = stop
        k = int(np.searchsorted(self._buf.t, hi_rig, side="left"))
        out, self._buf = self._buf[:k], self._buf[k:]
        return out

    def _slice(self, t0: float, t1: float, shift: float) -> _Packet | None:
        """The recorded data of true time [t0, t1), in the sensor clock, encoded."""
        assert self._take is not None
        track = self._track
        lo_rig = None if math.isinf(t0) else math.ceil(t0 + shift)
        hi_rig = math.ceil(t1 + shift)
        ev = self._take_until(hi_rig)
        t_dev, inexact = rig_to_device(track.cmap, ev.t)
        a = 0 if lo_rig is None else int(np.searchsorted(track.trig_rig, lo_rig, side="left"))
        b = int(np.searchsorted(track.trig_rig, hi_rig, side="left"))
        t_dev -= self._base
        trig = TriggerEvents(track.trig_device[a:b] - self._base, track.trig_p[a:b], track.trig_channel[a:b])
        n = len(ev)
        events = ev.with_time(t_dev)
        # Time words up to the slice end: the host knows how far the stream got, events or not.
        end_device, _ = rig_to_device(track.cmap, np.array([hi_rig - 1], np.int64))
        payload = self._encoder.encode(events, trig) + self._encoder.mark_time(
            int(end_device[0]) - self._base
        )
        with self._lock:
            self._counts["events"] += n
            self._counts["triggers"] += b - a
            self._counts["bytes"] += len(payload)
            self._counts["inexact_times"] += inexact
        return _Packet(
            payload,
            self.host_clock.now_ns(),
            n,
            b - a,
            int(t_dev[0]) if n else 0,
            int(t_dev[-1]) if n else 0,
            t1,
        )


def open_replay_event_sensor(spec: DeviceSpec) -> ReplayEventSensor:
    """Factory for `replay:///abs/take.h5?device=ev0[&buffer_packets=&unplug_at_s=]`."""
    check_params(spec, ReplaySensorParams, f"replayed event sensor {spec.params.get('device', '?')}")
    world, rec, timeline = replay_world(spec)
    buffer_packets = buffers_param(spec, "buffer_packets", 1024)
    return ReplayEventSensor(
        spec,
        world,
        rec,
        timeline,
        buffer_packets=buffer_packets,
        unplug=unplug_params(spec),
        clock_reset=clock_reset_param(spec),
    )
