"""One channel per device for the length of a take: read it, bring it back, hand data on.

A camera or event sensor channel reads its device on its own thread, reconnects a device
that drops out (every `reconnect_interval_s` until the take ends), re-ties the clock of a
device that comes back counting from zero (`clock_reset`), and puts what it read on the
writer queue. The trigger channel reads the box's pulse records. What reached the file
(`written`, the trigger observations the sync engine fits) the writer thread records in the
channel's `stream` (`streams`), never by calling the channel.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Any, Generic

import numpy as np
from numpy.typing import NDArray

from drivers.base import Capability, Trigger
from drivers.registry import open_device
from rigd.app.capture.clock_reset import MAX_HOLD_S, MAX_OBSERVATIONS, ClockReset, estimate_offset
from rigd.app.capture.control import RunControl
from rigd.app.capture.faults import FaultBoard
from rigd.app.capture.gate import WindowGate
from rigd.app.capture.items import PulsesItem, WriterQueue
from rigd.app.capture.ledger import LossLedger
from rigd.app.capture.live import Gap, LiveStats
from rigd.app.capture.overload import Shedding
from rigd.app.capture.reading import DevT, ItemT, Reading
from rigd.app.capture.streams import DeviceStream
from rigd.app.capture.window import TakeWindow
from rigd.core.devices import PulseBatch
from rigd.core.errors import DeviceError, RigdError
from rigd.core.events import EventArray
from rigd.core.host_clock import HostClock
from rigd.core.schema import LossKind
from rigd.core.settings import TriggerSettings
from rigd.sync import PulseLog
from rigd.take.writer import TakeWriter

log = logging.getLogger(__name__)

READ_TIMEOUT_S = 0.05


def pace(done: threading.Event, asked: float) -> None:
    """After an empty read: wait out the rest of the read timeout. A device that is not
    acquiring (not started yet, stopped, draining) answers at once, and an acquisition
    thread that asked again at once would spin and starve the others of the GIL."""
    rest = READ_TIMEOUT_S - (time.monotonic() - asked)
    if rest > 0:
        done.wait(rest)


def pulse_log(batches: list[PulseBatch], emitted: int) -> PulseLog:
    """The box's pulse records so far, one per index."""
    if not batches:
        none = np.empty(0, np.int64)
        return PulseLog.from_records(none, none, none, emitted)
    return PulseLog.from_records(
        np.concatenate([b.index for b in batches]),
        np.concatenate([b.t_us for b in batches]),
        np.concatenate([b.host_time_ns for b in batches]),
        emitted,
    )


class TriggerChannel:
    """The trigger box: its pulse records, kept for the sync engine and written to the take."""

    def __init__(
        self,
        spec: str,
        settings: TriggerSettings,
        control: RunControl,
        faults: FaultBoard,
        live: LiveStats,
        window: TakeWindow | None = None,
        *,
        device: Trigger | None = None,
    ) -> None:
        #: `device`: a trigger opened elsewhere (a follower host's `RemoteTrigger`) instead of `spec`'s.
        self.device: Trigger = open_device("trigger", spec) if device is None else device
        self.window = window
        """The take's trigger window, told of every pulse record."""
        self.settings = settings
        self.live = live
        self._control = control
        self._faults = faults
        self._lock = threading.Lock()
        self._batches: list[PulseBatch] = []
        self.n_pulses = 0
        self.pulses_after_window = 0
        """Pulse records after the take window's last pulse, not kept."""

    def configure(self) -> None:
        self.device.configure(self.settings)

    def run(self, queue: WriterQueue) -> None:
        """The acquisition thread body: pulse records until acquisition ends."""
        while True:
            asked = time.monotonic()
            batch = self.device.read_pulses(READ_TIMEOUT_S)
            if len(batch) and self.window is not None:
                self.window.note_pulses(batch.index, batch.t_us, batch.host_time_ns)
                batch = self._clip(batch, self.window.last_index)
            if len(batch):
                with self._lock:
                    self._batches.append(batch)
                    self.n_pulses += len(batch)
                    self.live.total = self.n_pulses
                self.live.last_data_mono = time.monotonic()
                queue.put(PulsesItem(batch), self.live)
            elif self._control.acquiring_done.is_set():
                return
            else:
                pace(self._control.acquiring_done, asked)

    def _clip(self, batch: PulseBatch, last: int | None) -> PulseBatch:
        """Pulse records past the take's last pulse (the box ran on during STOP's round trip)
        are counted in `pulses_after_window`, not kept."""
        if last is None:
            return batch
        keep = batch.index <= last
        if keep.all():
            return batch
        self.pulses_after_window += int(np.count_nonzero(~keep))
        return PulseBatch(batch.index[keep], batch.t_us[keep], batch.host_time_ns[keep])

    def pulses(self, emitted: int = 0) -> PulseLog:
        with self._lock:
            batches = list(self._batches)
        return pulse_log(batches, emitted)

    def records_since(self, since: int) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
        """Index, box time and host arrival time of the kept records with index >= `since`
        (a follower host's feed)."""
        with self._lock:
            batches = list(self._batches)
        tail: list[PulseBatch] = []
        for b in reversed(batches):
            if not len(b):
                continue
            tail.append(b)
            if int(b.index[0]) <= since:
                break
        if not tail:
            return np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, np.int64)
        index = np.concatenate([b.index for b in reversed(tail)])
        t_us = np.concatenate([b.t_us for b in reversed(tail)])
        host = np.concatenate([b.host_time_ns for b in reversed(tail)])
        keep = index >= since
        return index[keep], t_us[keep], host[keep]

    def last_pulse_host_ns(self) -> int | None:
        """When the newest pulse record reached the host (monotonic ns)."""
        with self._lock:
            stamps = [int(b.host_time_ns.max()) for b in self._batches if len(b)]
        return max(stamps, default=None)

    def stop_box(self) -> int:
        """STOP the pulses; the number emitted (what was seen, when the box does not answer)."""
        try:
            return self.device.stop()
        except DeviceError as exc:
            with self._lock:
                seen = max((int(b.index.max()) + 1 for b in self._batches if len(b)), default=0)
            self._faults.note(f"the trigger box did not confirm STOP ({exc}); {seen} pulses assumed")
            log.error("trigger STOP failed (%s); assuming %d pulses", exc, seen)
            return seen


@dataclass(frozen=True, slots=True)
class ChannelContext:
    """What every device channel of a take shares."""

    control: RunControl
    queue: WriterQueue
    ledger: LossLedger
    faults: FaultBoard
    trigger: TriggerChannel
    period_us: float
    reconnect_interval_s: float

    @property
    def host_clock(self) -> HostClock:
        """The clock the take's host times are on: the trigger's (its pulse records'), which the
        session checked the devices stamp with too. Comparing an item's host time with "now"
        asks this clock; the daemon's own waits stay on wall time."""
        return self.trigger.device.host_clock


class DeviceChannel(Generic[DevT, ItemT]):
    """A camera or event sensor, from opening to the end of the take: one loop for every kind,
    composed from its kind's parts (`kinds.open_channels` picks them): `reading` (open,
    configure, read, what an item says about time), `gate` (the take window, set once the
    window can be placed: `open_gate`), `shedding` (what goes to the writer under overload)
    and `stream` (how the writer thread writes and observes its items)."""

    def __init__(
        self,
        name: str,
        spec: str,
        settings_json: str,
        reading: Reading[DevT, ItemT],
        stream: DeviceStream[Any],
        shedding: Shedding[ItemT],
        ctx: ChannelContext,
    ) -> None:
        self.name = name
        self.spec = spec
        self.settings_json = settings_json
        """The config entry's settings, as the take stores them."""
        self.reading: Reading[DevT, ItemT] = reading
        self.stream = stream
        """How the device's items are written and observed; the writer thread records there
        what reached the file."""
        self.shedding: Shedding[ItemT] = shedding
        self.ctx = ctx
        self.live = stream.live
        self.what: LossKind = reading.what
        self.clock_reset: ClockReset[ItemT] | None = None
        self.gate: WindowGate[ItemT] | None = None
        """Keeps what lies outside the take's trigger window out of the file (counted)."""
        self.read_deadline: float | None = None
        """Monotonic time after which, once acquisition is done, the channel stops reading
        what the stopped device still holds (`writer.stop_backlog_s`)."""
        self.left_unread = False
        """The device still had data when `read_deadline` passed."""
        self.device: DevT = reading.open(spec)

    # -- lifecycle ------------------------------------------------------------------------
    def required_capabilities(self) -> frozenset[Capability]:
        """What the device must be able to do for its settings (checked by the preflight)."""
        return self.reading.required_capabilities(self.device)

    def configure(self) -> None:
        """Apply the config entry's settings."""
        self.reading.configure(self.device)

    def open_gate(self, window: TakeWindow, hold_s: float) -> None:
        """Place the device's data in the take window from here on."""
        self.gate = self.reading.gate(self.device, window, hold_s, self.ctx.host_clock)

    def add_to_take(self, take: TakeWriter) -> None:
        self.reading.add_to_take(take, self.device, self.settings_json)

    def software_synced(self) -> bool:
        return self.reading.software_synced(self.device)

    def ballast_bytes(self) -> int:
        return self.reading.ballast_bytes(self.device)

    def event_view(self) -> tuple[EventArray, tuple[int, int]] | None:
        """The newest events written and the sensor's geometry (None: no events to show)."""
        return self.reading.event_view(self.device, self.stream)

    def stop(self) -> None:
        """Stop acquiring at the end of the take; a device away or written off is left to
        its acquisition thread."""
        if self.live.state != "ok":
            return
        try:
            self.device.stop()
        except DeviceError as exc:
            if not self.ctx.ledger.is_written_off(self.name):
                raise
            log.warning("stopping failed device %s: %s", self.name, exc)

    def close(self) -> None:
        try:
            self.device.close()
        except RigdError as exc:
            log.error("closing %s failed: %s", self.device.info.spec, exc)

    def drained(self, last_pulse_host_ns: int | None, period_ns: int) -> bool:
        """Whether the device has delivered what belongs to the last pulse: a camera the frame
        it exposed on it, an event sensor data from two periods past it; a device away or
        written off is not waited for."""
        if self.live.state != "ok" or last_pulse_host_ns is None:
            return True
        newest = self.live.last_host_ns
        wait_ns = self.stream.drain_periods * period_ns
        return newest is not None and newest >= last_pulse_host_ns + wait_ns

    def window_reached(self) -> bool:
        """Whether the device has delivered up to the end of the take window (nothing of the
        window is still to come from it); a device away or written off, or a take without a
        known window end, is not waited for."""
        gate = self.gate
        if self.live.state != "ok" or gate is None or gate.end_device_us is None:
            return True
        return gate.reached_end()

    def collect_counters(self) -> None:
        """Turn the device's counters into loss records: what the device lost, what the
        host's decoder had to skip, and trigger edges that could not be delivered in order."""
        ledger, name = self.ctx.ledger, self.name
        try:
            stats = self.device.stats()
        except DeviceError as exc:
            if not ledger.is_written_off(name):
                raise
            log.warning("no counters from failed device %s: %s", name, exc)
            return
        ledger.set_counters(
            name, {"delivered": stats.delivered, "device_dropped": stats.device_dropped, **stats.extra}
        )
        if stats.device_dropped:
            ledger.add(
                name,
                self.what,
                stats.device_dropped,
                "lost inside the device or its transport (device counters)",
            )
        prefix = "decoder_skipped_"
        skipped = {k.removeprefix(prefix): v for k, v in stats.extra.items() if k.startswith(prefix) and v}
        if skipped:
            ledger.add(name, "events", sum(skipped.values()), f"EVT decoder skipped invalid data: {skipped}")
        if stats.extra.get("triggers_ignored"):
            ledger.add(
                name,
                "frames",
                stats.extra["triggers_ignored"],
                "trigger edges arrived while the camera was busy (slower than the trigger)",
            )
        if skipped_s := stats.extra.get("lag_skipped_us", 0) / 1e6:
            times = stats.extra.get("lag_skips", 0)
            why = f"the simulator fell behind real time and did not make {skipped_s:.2f} s of events"
            ledger.add(
                name, "events", 0, f"{why} ({times} time(s); count unknown; a virtual clock never does)"
            )
        if stats.extra.get("triggers_late"):
            ledger.add(
                name,
                "triggers",
                stats.extra["triggers_late"],
                "trigger edges arrived after their part of the stream was sent",
            )

    # -- the acquisition thread ------------------------------------------------------------
    def run(self) -> None:
        """Read until the take ends. A device that fails for good (unplugged and not back,
        say) is written off with a loss record and the take goes on with the others."""
        try:
            self._read_loop()
        except DeviceError as exc:
            log.error("device %s failed mid-take, the others go on: %s", self.name, exc)
            self.ctx.faults.set("device_failed", self.name, f"{self.name} written off: {exc}")
            with self.live.lock:
                self.live.state = "failed"
            self.ctx.ledger.write_off(self.name, self.what, str(exc), self.live.last_t)

    def _read_loop(self) -> None:
        done = self.ctx.control.acquiring_done
        try:
            self._read_until_done(done)
        finally:
            if self.gate is not None:
                for part in self.gate.finish():
                    self._enqueue(part)
            self.shedding.close()

    def _read_until_done(self, done: threading.Event) -> None:
        while True:
            asked = time.monotonic()
            if done.is_set() and self.read_deadline is not None and asked > self.read_deadline:
                self._stop_reading()
                return
            reading, dev = self.reading, self.device  # a reconnect replaces the device
            try:
                item = reading.read(dev, READ_TIMEOUT_S)
            except DeviceError as exc:
                if done.is_set():
                    raise
                self._reconnect(exc)
                continue
            if item is not None:
                self._deliver(item)
            self._note_stream_time(reading.stream_time_us(dev))
            if item is not None:
                reading.pace(done, asked, time.monotonic())
            if item is None:
                if done.is_set():
                    self._drop_held("the take ended before its restarted clock could be tied")
                    return
                pace(done, asked)

    def _note_stream_time(self, t: int | None) -> None:
        """How far a sensor's stream has got, events or not, for its window gate (on the old
        clock of a sensor that came back restarted; not before that clock is tied again)."""
        gate = self.gate
        if gate is None or t is None:
            return
        reset = self.clock_reset
        if reset is not None:
            if reset.offset is None:
                return
            t += reset.offset.us
        gate.note_stream_time(t)

    def _stop_reading(self) -> None:
        """The stop's bound ran out while the stopped device still delivered: leave the rest in
        its buffers, recorded (its own counters give the amount where it keeps them)."""
        self._drop_held("the take ended before its restarted clock could be tied")
        dev = self.device
        try:
            more = self.reading.read(dev, 0.0)
        except DeviceError as exc:
            log.warning("%s: last read at the stop bound failed: %s", self.name, exc)
            return
        if more is None:
            return
        self._deliver(more)
        self.left_unread = True
        reached = None if self.gate is None else self.gate.reached_us
        log.warning("%s: still delivering at the stop bound; the rest of its buffers is not read", self.name)
        self.ctx.ledger.add(
            self.name,
            self.what,
            0,
            "left unread in the stopped device's buffers when writer.stop_backlog_s ran out "
            "(count unknown: see the device's counters; past the take window when its gate was closed)",
            (reached, None),
        )

    def _reconnect(self, exc: DeviceError) -> None:
        """Keep trying to open the device again until it answers or the take ends (then it
        is written off by `run`)."""
        live, faults = self.live, self.ctx.faults
        with live.lock:
            live.state = "reconnecting"
            if live.gap is None:
                live.gap = Gap(time.monotonic(), live.last_t, str(exc))
            since = live.gap.since_mono
        faults.set("device_reconnecting", self.name, f"{self.name} lost ({exc}); reconnecting")
        try:
            self.device.close()
        except DeviceError as close_exc:
            log.warning("closing lost device %s: %s", self.name, close_exc)
        if self.ctx.reconnect_interval_s <= 0:
            raise exc
        while not self.ctx.control.acquiring_done.wait(self.ctx.reconnect_interval_s):
            try:
                dev = self.reading.open(self.spec)
                try:
                    self.reading.configure(dev)
                    dev.start()
                except BaseException:
                    dev.close()
                    raise
            except DeviceError as again:
                log.info("device %s still away: %s", self.name, again)
                continue
            self.device = dev
            with live.lock:
                live.state = "ok"
                live.reconnects += 1
            log.warning("device %s reconnected after %.1f s", self.name, time.monotonic() - since)
            faults.clear("device_reconnecting", self.name)
            return
        faults.clear("device_reconnecting", self.name)
        raise DeviceError(f"{self.name} did not come back before the end of the take (lost: {exc})") from exc

    # -- delivery -------------------------------------------------------------------------
    def _deliver(self, item: ItemT) -> None:
        """One frame or event packet on its way to the writer; a device that came back with
        its clock restarted is re-tied onto its old clock first."""
        reset = self.clock_reset
        if (t_before := self._restarted(item, reset)) is not None:
            reset = self.clock_reset = ClockReset(self.name, self.reading, t_before)
            log.warning("%s came back with its clock restarted; tying it to its old clock", self.name)
        if reset is None:
            self._pass(item)
            return
        if reset.offset is not None:
            self._pass(reset.shift(item))
            return
        seen = len(reset.post_t)
        reset.hold(item)
        if len(reset.post_t) == seen and reset.held_for_s() <= MAX_HOLD_S:
            return  # nothing new to tie with (an event packet without trigger edges)
        if not self._tie(reset):
            return
        for held in reset.release():
            self._pass(held)

    def _restarted(self, item: ItemT, reset: ClockReset[ItemT] | None) -> int | None:
        """For a first delivery after a reconnect whose time lies before the last one before
        the gap: that last time (the device's clock restarted); else None. A device already
        re-tied is compared on its old clock (it may restart again); one still being tied is
        not asked (its gap stays open until it is)."""
        gap = self.live.gap
        t = self.reading.times(item)[0]
        if reset is not None:
            if reset.offset is None:
                return None
            t = None if t is None else t + reset.offset.us
        if gap is None or gap.t_before is None or t is None or t >= gap.t_before:
            return None
        return gap.t_before

    def _tie(self, reset: ClockReset[ItemT]) -> bool:
        """Try to place the restarted clock on the old one; True once done. A device that does
        not tie within MAX_OBSERVATIONS is written off (what was held is counted lost)."""
        pre_t, pre_host, _ = self.stream.obs.arrays()
        n = min(pre_t.size, pre_host.size)
        offset = estimate_offset(
            reset, pre_t[:n], pre_host[:n], self.ctx.trigger.pulses(), self.ctx.period_us
        )
        if offset is None:
            if len(reset.post_t) >= MAX_OBSERVATIONS or reset.held_for_s() > MAX_HOLD_S:
                self._drop_held("its restarted clock could not be tied to the trigger pulses")
                self._stop_written_off()
                raise DeviceError(
                    f"{reset.name} came back with its clock restarted and {len(reset.post_t)} trigger "
                    f"observations in {MAX_HOLD_S:g} s did not tie it to its old clock; written off from here"
                )
            return False
        reset.offset = offset
        line = (
            f"{reset.name} came back with its clock restarted: its device times from then on are "
            f"shifted by {offset.us} us onto its old clock ({offset.n} trigger observations, "
            f"spread {offset.spread_us:.1f} us)"
        )
        log.warning("%s", line)
        self.ctx.faults.note(line)
        return True

    def _stop_written_off(self) -> None:
        """A live device about to be written off stops acquiring (bus bandwidth, its buffers)."""
        try:
            self.device.stop()
        except DeviceError as exc:
            log.warning("stopping %s before writing it off: %s", self.name, exc)

    def _drop_held(self, why: str) -> None:
        reset = self.clock_reset
        if reset is None or not reset.held:
            return
        count = reset.held_count()
        reset.held.clear()
        self.ctx.ledger.add(self.name, self.what, count, f"held back and not written: {why}")

    def _pass(self, item: ItemT) -> None:
        t_first, t_last = self.reading.times(item)
        self._arrived(t_first, t_last, item.host_time_ns)
        anchors = self.reading.anchors
        if anchors is not None and t_last is not None:
            anchors.note(t_last, item.host_time_ns)
        gate = self.gate
        for part in [item] if gate is None else gate.admit(item):
            self._enqueue(part)

    def _enqueue(self, item: ItemT) -> None:
        queue = self.ctx.queue
        kept = self.shedding.admit(item, queue.fill(), self.ctx.host_clock.now_ns())
        if kept is not None:
            queue.put(self.reading.queue_item(kept), self.live)

    def _arrived(self, t_device: int | None, t_last: int | None, host_ns: int) -> None:
        """Bookkeeping for one delivery; closes a reconnect gap with its loss record."""
        live = self.live
        live.last_data_mono = time.monotonic()
        live.last_host_ns = host_ns
        if t_device is None:
            return
        gap = live.gap
        if gap is not None:
            if gap.t_before is not None and t_device < gap.t_before:
                raise DeviceError(
                    f"{self.name} came back with its clock reset ({t_device} us after {gap.t_before} us) "
                    "and was tied wrongly; written off from here"
                )
            away = time.monotonic() - gap.since_mono
            with live.lock:
                live.gap = None
            self.ctx.ledger.add(
                self.name,
                self.what,
                0,
                f"device away for {away:.2f} s ({gap.why}); reconnected, nothing recorded in "
                "between (count unknown: see t_first_us..t_last_us and the sync report)",
                (gap.t_before, t_device),
            )
        live.last_t = t_device if t_last is None else t_last
