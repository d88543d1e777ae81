"""Simulated event sensor: ideal change-detection pixels watching the scene in real time.

The acquisition thread (the sensor's firmware) wakes every `SLICE_US` of true time and
produces the events of the elapsed interval with the ideal-pixel kernels of
`firmware_sim.event_kernels`, which render only what moves. With `pixel_model=full` in the
spec the sensor runs `firmware_sim.event_model` (mismatch, noise, refractory, low-pass) on
whole rendered frames instead.

The sensor talks like a Prophesee camera: each slice's events and trigger-in edges are
encoded into an EVT 3.0 byte stream (time-ordered, trigger edges interleaved), and the host
side is the production `drivers.evt_stream.DecodingEventSensor`, which decodes it. The generator
runs `GENERATION_LAG_US` behind true time so the trigger box's edges for a slice are latched
before the slice is encoded; an edge later than that cannot be placed in the time-ordered
stream and is counted (`triggers_late`), never dropped silently. Buffers go into a bounded
FIFO whose overflows are counted.

`unplug_at_s` / `unplug_for_s` take the sensor off the bus (docs/sim-faults.md): `read_events`
raises DeviceError, which the capture pipeline gets as from a real camera, the generator stops,
and the span of true time whose events the host never got goes into the ground truth
(`GroundTruth.unplugged`).
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from drivers.base import Capability
from drivers.evt_stream import DecodingEventSensor, EvtBuffer
from drivers.lifecycle import END, Signal
from drivers.registry import DeviceSpec
from firmware_sim.clock import Hold
from firmware_sim.event_kernels import (
    MAX_STEP_PX,
    MAX_STEP_US,
    EventBuffer,
    generate_events,
    warm_up_generator,
)
from firmware_sim.event_model import EventSimulator, PixelModelConfig
from firmware_sim.placement import Placement, check_ranges, ground_truth_facts, place
from firmware_sim.scene import lin_log
from firmware_sim.spec_params import SimEventSensorParams, check_params
from firmware_sim.world import DeviceClock, Edge, Unpluggable, truth_journal, wait_for_room
from rigd.core.devices import DeviceInfo
from rigd.core.errors import ConfigError
from rigd.core.events import EventArray, TriggerEvents
from rigd.evt import Evt3Encoder

log = logging.getLogger(__name__)

#: True time between generator wake-ups: each slice's events are one EVT buffer. 10 ms halves
#: the per-slice cost (geometry, sort, encoding, hand-over) of 5 ms slices; the renders inside a
#: slice stay at most `event_kernels.MAX_STEP_US` (5 ms) apart, so the events are the same.
SLICE_US = 10_000
#: On virtual time a sensor runs at most this many packets ahead of its reader.
_VIRTUAL_LEAD_PACKETS = 8
#: After stop, how long (wall seconds) a sensor on virtual time waits for room before dropping.
_STOP_ROOM_WAIT_S = 2.0
#: Packets merged into one `read_events` answer at most.
_MAX_MERGE = 64

_CAPABILITIES = frozenset({Capability.TRIGGER_IN, Capability.DEVICE_TIMESTAMPS, Capability.CLOCK_SYNC})


@dataclass(frozen=True, slots=True)
class SensorParams:
    """What an event sensor spec may set besides its placement."""

    threshold: float = 0.3
    buffer_packets: int = 1024
    pixel_model: PixelModelConfig | None = None
    """None: the fast ideal kernel (rendering only what moves). Otherwise the full pixel model
    of `firmware_sim.event_model` (noise, mismatch, refractory, low-pass) on whole rendered log
    frames at every sub-step: real time only at small resolutions."""


@dataclass(frozen=True, slots=True)
class _Packet(EvtBuffer):
    """One slice's EVT buffer, with what the ground truth and the journal need to know of it."""

    n_events: int
    n_triggers: int
    t_first_us: int
    """Device time of the first event (0 when there is none)."""
    t_last_us: int
    true_end_us: float
    """True time the slice ends: the host has every event before it once it read this packet."""


@dataclass(slots=True)
class _Generator:
    """Where the firmware's generator stands: end of the last slice, log image and per-pixel
    reference at that time, the full pixel model if any, and whether the final slice is out."""

    t_prev: float
    last_log: NDArray[np.float32]
    ref: NDArray[np.float32]
    model: EventSimulator | None
    final: bool = False
    hold: Hold | None = None
    """On virtual time: holds the world's time while a slice is made and delivered."""
    buf: EventBuffer = field(default_factory=EventBuffer)
    """The kernels' output, reused slice after slice (it keeps the size the busiest slice needed)."""


#: How far behind true time the generator encodes, so trigger edges are in before their slice.
GENERATION_LAG_US = 50_000
#: Real time only: a generator further behind than this skips ahead (counted, `lag_skipped_us`).
MAX_LAG_US = 1_000_000
#: Real time only: at stop, at most this much true time after the last slice is still made.
_STOP_CATCH_UP_US = GENERATION_LAG_US + 2 * SLICE_US


class SimEventSensor(Unpluggable, DecodingEventSensor[_Packet]):
    """An ideal event sensor in a `SimWorld`, with its own drifting clock and trigger-in.

    It hands out EVT 3.0 buffers, as a camera would, and the host decodes them
    (`drivers.evt_stream.DecodingEventSensor`). Its firmware runs on the acquisition thread:
    every slice it generates the events since the last one, takes the trigger edges latched up
    to then and encodes both into one buffer of the on-sensor FIFO (`buffer_packets` long; a
    packet that finds it full is lost, counted: `packets_dropped`, its events in
    `device_dropped`).
    """

    _device_label = "event sensor"
    _capabilities = _CAPABILITIES
    _overflow_name = "packets_dropped"
    _overflow_is_loss = False  # counted in events, by `_deliver`

    def __init__(self, where: Placement, params: SensorParams | None = None) -> None:
        p = params or SensorParams()
        world, name = where.world, where.name
        if p.threshold <= 0:
            raise ConfigError(f"event sensor {name}: threshold must be > 0, got {p.threshold}")
        if p.buffer_packets < 1:
            raise ConfigError(f"event sensor {name}: buffer_packets must be >= 1, got {p.buffer_packets}")
        super().__init__(
            "evt3",
            (where.width, where.height),
            buffers=p.buffer_packets,
            merge=_MAX_MERGE,
            drain_on_stop=True,
        )
        self._world, self._name, self._scene, self._clock, self._p = world, name, where.scene, where.clock, p
        self._unplug = where.unplug
        self._view = where.scene.view(name, where.width, where.height)
        self._info = DeviceInfo(
            kind="event_sensor",
            spec=where.spec,
            vendor="rigd-sim",
            model="SimEventSensor",
            serial=f"{world.name}/{name}",
            firmware="sim-1",
            facts={
                "evt_format": "evt3",
                "pixel_model": "ideal",
                "threshold": str(p.threshold),
                **ground_truth_facts(where),
            },
        )
        self._plug_in(world, name, self._info.spec)
        self._delivered_until_us = -math.inf
        self._journal = truth_journal()
        self._journal_head = f'{{"world":{json.dumps(world.name)},"dev":{json.dumps(name)},"kind":"events"'
        world.register_clock(name, where.clock)
        self._lock = threading.Lock()
        self._accepting = False
        self._generating = False
        self._pending: list[tuple[float, int]] = []
        self._encoder = Evt3Encoder()
        self._encoded_until_us = -math.inf
        self._events_lost = 0
        self._model_t = 0
        self._gen = _Generator(0.0, np.zeros((0, 0), np.float32), np.zeros((0, 0), np.float32), None)
        self._counts = {
            "triggers_dropped": 0,
            "triggers_late": 0,
            "events_generated": 0,
            "triggers": 0,
            "bytes": 0,
            "packets_lost_unplugged": 0,
            "lag_skipped_us": 0,
            "lag_skips": 0,
            "stop_not_made_us": 0,
        }
        # Every sim device hears the trigger wire and its unplug fault the same way (two calls
        # alike in the camera and the event sensor, each with its own counters above).
        self._unsubscribe = world.wire.subscribe(self._on_edge)
        self._unlisten = self._fault.listen(self._on_unplug)

    @property
    def clock(self) -> DeviceClock:
        return self._clock

    def _do_start(self) -> None:
        if self._settings.sync_mode == "slave":
            # A slave counts time on its master's clock (the sync cable): share that clock.
            master = self._settings.sync_master
            clocks = self._world.truth.clocks
            if master is None or master not in clocks:
                raise ConfigError(
                    f"event sensor {self._name}: sync master {master!r} is not a device of world "
                    f"{self._world.name!r} (sim device names must match the rig names)"
                )
            self._clock = clocks[master]
            self._world.register_clock(self._name, self._clock)
        t_start = self._world.now_us()
        last_log = lin_log(self._scene.render_intensity(self._view, t_start))
        model: EventSimulator | None = None
        if self._p.pixel_model is not None:
            model = EventSimulator(*self._geometry, self._p.pixel_model)
            self._model_t = round(t_start)
            model.step(last_log, self._model_t)
        hold = self._world.hold() if self._world.virtual else None
        self._gen = _Generator(t_start, last_log, last_log.copy(), model, hold=hold)
        with self._lock:
            self._pending.clear()
            self._accepting = True
            self._generating = True
            self._delivered_until_us = t_start
        self._arm_unplug(self._unplug, t_start, lost_frames_on_edges=False)
        log.info("event sensor %s started at true %.0f us", self._name, t_start)

    def warm_up(self) -> None:
        """Compile the firmware's kernels (render and compare, sort, EVT 3.0 encode; the full
        pixel model's when set) on throwaway state, before the take: a simulator compiling them
        on its first slices falls seconds behind real time and skips what it did not make."""
        t_us = self._world.now_us()
        events = warm_up_generator(self._scene, self._view, self._p.threshold, self._clock, t_us)
        if self._p.pixel_model is not None:
            model = EventSimulator(*self._geometry, self._p.pixel_model)
            for k in range(2):
                t = t_us + k * SLICE_US
                model.step(lin_log(self._scene.render_intensity(self._view, t)), round(t))
        triggers = TriggerEvents(np.array([0], np.int64), np.array([1], np.uint8), np.zeros(1, np.uint8))
        encoder = Evt3Encoder()
        encoder.encode(events.with_time(events.t - events.t.min()) if len(events) else events, triggers)
        encoder.encode(EventArray.empty(), TriggerEvents.empty())
        super().warm_up()

    def _do_stop(self) -> None:
        with self._lock:
            self._accepting = False
            self._generating = False

    def _do_close(self) -> None:
        self._unsubscribe()
        self._unlisten()
        if self._gen.hold is not None:
            self._gen.hold.release()
        super()._do_close()

    def _join(self, parts: list[_Packet]) -> tuple[bytes, int]:
        with self._lock:
            if self._dead(self._world.now_us()):  # unplugged while we waited: these are lost too
                self._note_unplug_locked(parts)
                raise self._unplugged_error()
            self._delivered_until_us = parts[-1].true_end_us
        if self._journal is not None:
            self._write_journal(parts)
        return super()._join(parts)

    def _write_journal(self, parts: list[_Packet]) -> None:
        """One line per buffer handed to the reader (a decoded `EventPacket`), never per event."""
        n = sum(pk.n_events for pk in parts)
        with_events = [pk for pk in parts if pk.n_events]
        first = str(with_events[0].t_first_us) if with_events else "null"
        last = str(with_events[-1].t_last_us) if with_events else "null"
        n_trig = sum(pk.n_triggers for pk in parts)
        assert self._journal is not None
        self._journal.write(
            f'{self._journal_head},"n":{n},"n_triggers":{n_trig},"t_first_device_us":{first},'
            f'"t_last_device_us":{last},"host_time_ns":{self.host_clock.now_ns()}}}'
        )

    def _counters(self) -> tuple[int, dict[str, int]]:
        with self._lock:
            counts = dict(self._counts)
            lost = self._events_lost
        _, decoder = super()._counters()
        return lost, {**counts, **decoder}

    # --- unplug fault ---------------------------------------------------------------------

    def _note_unplug_locked(self, lost: list[_Packet]) -> None:
        """Log what the unplug cost (caller holds the lock); safe to call more than once.

        Everything after the last slice the host read is lost: packets still queued, the
        slices the generator (running behind true time) had not encoded yet, and the window.
        """
        lost = [*lost, *self._queue.drain()]
        self._events_lost += sum(pk.n_events for pk in lost)
        self._counts["packets_lost_unplugged"] += len(lost)
        if not self._unplug_noted:
            self._unplug_noted = True
            self._accepting = False
            if self._generating:
                self._world.truth.add_unplugged(self._name, self._delivered_until_us, self._fault.end_us)
            log.warning(
                "event sensor %s unplugged; events after true %.0f us lost",
                self._name,
                self._delivered_until_us,
            )

    # --- trigger-in -----------------------------------------------------------------------

    def _on_edge(self, edge: Edge) -> None:
        """Runs on the trigger box's thread: only latch the edge."""
        with self._lock:
            if not (self._accepting and self._settings.enable_trigger_in) or self._dead(edge.true_us):
                return
            if edge.true_us < self._encoded_until_us:
                self._counts["triggers_late"] += 1
                log.warning(
                    "event sensor %s: trigger edge at true %.0f us arrived after its slice was encoded",
                    self._name,
                    edge.true_us,
                )
                return
            self._pending.append((edge.true_us, 1 if edge.rising else 0))

    def _take_triggers(self, t_end_us: float | None) -> TriggerEvents:
        """Pending edges before `t_end_us` (all of them when None), stamped in the sensor clock."""
        with self._lock:
            self._pending.sort()
            if t_end_us is None:
                taken, self._pending = self._pending, []
            else:
                n = 0
                while n < len(self._pending) and self._pending[n][0] < t_end_us:
                    n += 1
                taken, self._pending = self._pending[:n], self._pending[n:]
        if not taken:
            return TriggerEvents.empty()
        t = np.array([self._clock.stamp(tu) for tu, _ in taken], np.int64)
        pol = np.array([p for _, p in taken], np.uint8)
        ch = np.full(len(taken), self._settings.trigger_in_channel, np.uint8)
        return TriggerEvents(t, pol, ch)

    # --- generator ------------------------------------------------------------------------

    def _model_events(self, model: EventSimulator, t0: float, t1: float) -> EventArray:
        """Full pixel model: whole log frames at sub-steps of at most MAX_STEP_PX of motion
        and MAX_STEP_US of time."""
        times, _ = self._scene.step_homographies(self._view, t0, t1, MAX_STEP_PX, MAX_STEP_US)
        parts = []
        for t in times[1:]:
            ti = round(t)
            if ti <= self._model_t:
                continue
            parts.append(model.step(lin_log(self._scene.render_intensity(self._view, t)), ti))
            self._model_t = ti
        ev = EventArray.concatenate(parts)
        # Model times are true-time microseconds: latch them on the sensor's own clock.
        t_dev = np.floor(self._clock.offset_us + ev.t.astype(np.float64) * self._clock.rate).astype(np.int64)
        return ev.with_time(t_dev)

    def _grab(self, timeout_s: float) -> _Packet | Signal | None:
        """One slice: wait until it is due (or stop() is asked), then generate and encode it.

        Runs `GENERATION_LAG_US` behind true time so the slice's trigger edges are latched;
        at stop everything up to now goes out (no later edge can belong to it) and the next
        call ends the thread. None when the slice holds nothing.
        """
        gen = self._gen
        if gen.final:
            if gen.hold is not None:
                gen.hold.release()
            return END
        wake = gen.t_prev + SLICE_US + GENERATION_LAG_US
        if gen.hold is not None:
            # Virtual time: whole slices on a fixed grid, so the same world gives the same events.
            stopping = not gen.hold.sleep_until(wake, self._stop_asked)
            t_now = self._world.now_us() if stopping else gen.t_prev + SLICE_US
        else:
            stopping = self._stop_asked.wait(max(0.0, (wake - self._world.now_us()) * 1e-6))
            t_now = self._world.now_us() - (0 if stopping else GENERATION_LAG_US)
            # A sensor cannot fall behind real time; a simulator on a busy CPU can. Past a bound
            # it skips ahead (and at stop it makes one slice more, not the whole backlog): the
            # skipped span is counted, so the host records it and stopping stays bounded.
            limit = gen.t_prev + (_STOP_CATCH_UP_US if stopping else MAX_LAG_US)
            if t_now > limit:
                self._skip(gen, limit if stopping else gen.t_prev, t_now, restart=not stopping)
                if stopping:
                    t_now = limit
        if self._dead(self._world.now_us()):
            with self._lock:
                self._note_unplug_locked([])
            if gen.hold is not None:
                gen.hold.release()  # a dead sensor no longer holds the world's time
            return END  # no power, no events
        if t_now <= gen.t_prev and not stopping:
            return None
        if gen.model is not None:
            events = self._model_events(gen.model, gen.t_prev, t_now)
        else:
            gen.buf.n = 0
            generate_events(
                self._scene,
                self._view,
                gen.last_log,
                gen.ref,
                self._p.threshold,
                gen.t_prev,
                t_now,
                self._clock,
                gen.buf,
            )
            events = gen.buf.to_array()
        with self._lock:
            self._encoded_until_us = t_now
        triggers = self._take_triggers(None if stopping else t_now)
        gen.t_prev = t_now
        gen.final = stopping
        return self._encode(events, triggers, t_now)

    def _skip(self, gen: _Generator, start: float, t_to: float, *, restart: bool) -> None:
        """Give up generating true time [start, t_to) (real time only). Running (`restart`),
        the span is counted as lost (`lag_skipped_us`), its trigger edges are dropped (counted)
        and the pixels restart at `t_to`. Stopping, the span after the last slice is simply not
        made, as a stopped sensor makes nothing (`stop_not_made_us`; the host asked for the
        stop, and a window it still needed is recorded by the capture as not delivered)."""
        if not restart:
            with self._lock:
                self._counts["stop_not_made_us"] += round(t_to - start)
            log.info("event sensor %s: stopped %.2f s behind real time", self._name, (t_to - start) / 1e6)
            return
        log_now = lin_log(self._scene.render_intensity(self._view, t_to))
        if gen.model is not None:
            gen.model.step(log_now, round(t_to))
            self._model_t = round(t_to)
        gen.last_log[...] = log_now
        gen.ref[...] = log_now
        gen.t_prev = t_to
        dropped = self._take_triggers(t_to)
        with self._lock:
            self._counts["lag_skipped_us"] += round(t_to - start)
            self._counts["lag_skips"] += 1
            self._counts["triggers_dropped"] += len(dropped)
        log.warning(
            "event sensor %s: the simulator fell %.2f s behind real time; those events are not made",
            self._name,
            (t_to - start) / 1e6,
        )

    def _encode(self, events: EventArray, triggers: TriggerEvents, true_end_us: float) -> _Packet:
        """The slice's EVT buffer, ending with time words up to the slice end (as a sensor's
        periodic TIME_HIGH words do), so the host knows how far the stream got even when the
        scene is still."""
        n = len(events)
        payload = self._encoder.encode(events, triggers)
        mark = self._encoder.mark_time(self._clock.stamp(true_end_us) - 1)
        return _Packet(
            payload + mark,
            self.host_clock.now_ns(),
            n,
            len(triggers),
            int(events.t.min()) if n else 0,
            int(events.t.max()) if n else 0,
            true_end_us,
        )

    def _give_up_waiting(self) -> Callable[[], bool]:
        """When a sensor waiting for room stops waiting: unplugged, or stopped for a while
        (the host may have stopped reading)."""
        stopped_since: list[float] = []

        def give_up() -> bool:
            if self._dead(self._world.now_us()):
                return True
            if not self._stopping:
                return False
            stopped_since[:] = stopped_since or [time.monotonic()]
            return time.monotonic() - stopped_since[0] > _STOP_ROOM_WAIT_S

        return give_up

    def _deliver(self, packet: _Packet) -> bool:
        """Into the FIFO, under the lock, so an unplug noted meanwhile finds it queued or not
        at all; a full FIFO loses it (counted with its events and trigger edges)."""
        if self._gen.hold is not None:
            # Virtual time waits for the host to make room instead of losing the packet.
            wait_for_room(self._queue, _VIRTUAL_LEAD_PACKETS, self._give_up_waiting())
        with self._lock:
            full = False
            if self._dead(self._world.now_us()):
                self._note_unplug_locked([packet])
            elif self._queue.put(packet) is not None:
                full = True
                self._events_lost += packet.n_events
                self._counts["triggers_dropped"] += packet.n_triggers
            self._counts["events_generated"] += packet.n_events
            self._counts["triggers"] += packet.n_triggers
            self._counts["bytes"] += len(packet.data)
        if full:
            log.warning(
                "event sensor %s: buffer full, dropped a packet of %d events, %d triggers",
                self._name,
                packet.n_events,
                packet.n_triggers,
            )
        return not full


#: Spec parameters of the full pixel model -> PixelModelConfig fields.
_MODEL_PARAMS = {
    "sigma": "sigma",
    "threshold_on": "threshold_on",
    "threshold_off": "threshold_off",
    "refractory_us": "refractory_us",
    "leak_hz": "leak_rate_hz",
    "shot_hz": "shot_noise_rate_hz",
    "hot_fraction": "hot_pixel_fraction",
    "lowpass_hz": "lowpass_cutoff_hz",
}


def _pixel_model(spec: DeviceSpec, seed: int) -> PixelModelConfig | None:
    kind = spec.param("pixel_model", "ideal")
    given = {k: v for k, v in _MODEL_PARAMS.items() if k in spec.params}
    if kind == "ideal":
        if given:
            raise ConfigError(f"device spec {spec.raw!r}: {', '.join(sorted(given))} need pixel_model=full")
        return None
    if kind != "full":
        raise ConfigError(f"device spec {spec.raw!r}: pixel_model={kind!r}; use ideal or full")
    fields: dict[str, object] = {"input_kind": "log", "threshold": spec.float_param("threshold", 0.3)}
    for key, field_name in given.items():
        fields[field_name] = spec.float_param(key, 0.0)
    if "lowpass_hz" in given:
        fields["lowpass"] = True
    fields["seed"] = seed
    try:
        return PixelModelConfig.model_validate(fields)
    except ValueError as exc:
        raise ConfigError(f"device spec {spec.raw!r}: {exc}") from None


def open_sim_event_sensor(spec: DeviceSpec) -> SimEventSensor:
    """Factory for `sim://<world>/<name>?threshold=&buffer_packets=&pixel_model=ideal|full`
    besides the placement parameters (`firmware_sim.placement`: offset_us, drift_ppm, seed,
    width, height, scene=sprites|board).

    Fault switches: `unplug_at_s=`, `unplug_for_s=`, `clock_reset=1` (docs/sim-faults.md).
    """
    check_params(spec, SimEventSensorParams, f"event sensor {spec.path.strip('/') or '?'}")
    where = place(spec, {"threshold", "buffer_packets", "pixel_model", *_MODEL_PARAMS})
    params = SensorParams(
        threshold=spec.float_param("threshold", 0.3),
        buffer_packets=spec.int_param("buffer_packets", 1024),
        pixel_model=_pixel_model(spec, where.seed),
    )
    check_ranges(
        spec,
        (
            ("threshold", params.threshold > 0 and math.isfinite(params.threshold)),
            ("buffer_packets", params.buffer_packets >= 1),
        ),
    )
    return SimEventSensor(where, params)
