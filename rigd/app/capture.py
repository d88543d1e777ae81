"""The capture pipeline: per-device acquisition threads, one bounded queue, one writer.

Acquisition threads only read from their device and enqueue; the writer thread owns the
take file. A full queue blocks an acquisition thread for `queue_put_timeout_s`, after
which the item is counted as lost with its time range, never dropped silently. After the
trigger box has emitted its pulses (or a stop was requested) the devices are drained, the
sync engine fits every device clock, and the writer maps all timestamps to rig time.

`CaptureSession` is the long-lived form the daemon uses: it runs in the background, can
be stopped, reports a live snapshot, watches the trigger link and the disk, and tries to
reconnect a device that disappears mid-take. `run_capture` is the blocking form.
"""

from __future__ import annotations

import errno
import functools
import json
import logging
import os
import queue
import shutil
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np

from drivers.base import EventPacket, EventSensor, RgbCamera, Trigger
from drivers.registry import open_device
from rigd import __version__
from rigd.app.clock_reset import MAX_HOLD_S, MAX_OBSERVATIONS, ClockReset, estimate_offset
from rigd.app.config import RigConfig
from rigd.core.devices import PulseBatch
from rigd.core.errors import DeviceError, RigdError, TakeError
from rigd.core.events import EventArray
from rigd.core.frames import Frame
from rigd.core.schema import LossKind, LossRecord, SyncReport
from rigd.sync import DeviceObservations, PulseLog, synchronize
from rigd.take.writer import TakeWriter

log = logging.getLogger(__name__)

#: How much later than its interval a flush may come before the writer counts as stalled.
FLUSH_STALL_SLACK_S = 2.0

_READ_TIMEOUT_S = 0.05
_STOP = object()
#: A trigger link with no valid line for this long (at rates where pulses come faster) is silent.
_TRIGGER_SILENT_S = 0.5
#: Device rates in telemetry are averaged over this many seconds.
_RATE_WINDOW_S = 2.0
#: Keep this many recent trigger observations per device for the live interval jitter.
_JITTER_WINDOW = 64

DeviceState = Literal["ok", "failed", "reconnecting", "idle"]
SessionState = Literal["new", "starting", "capturing", "stopping", "done", "failed"]


@dataclass(slots=True)
class Progress:
    """What the pipeline reports while it runs (for progress bars and telemetry)."""

    pulses: int
    pulses_total: int
    frames: dict[str, int]
    events: dict[str, int]
    queue_depth: int


@dataclass(slots=True)
class CaptureResult:
    path: Path
    report: SyncReport
    frames: dict[str, int]
    events: dict[str, int]
    bytes_written: int
    wall_s: float
    """Whole run: opening devices to closing the take."""
    capture_s: float
    """From the trigger's START until the writer had written everything."""
    flushes: int = 0
    flush_max_s: float = 0.0
    """The longest periodic flush (the writer thread's stall; `writer.fsync` lengthens it)."""
    end_reason: str = ""
    """Why the recording ended (also the take's `end_reason` attr)."""


@dataclass(slots=True)
class DeviceSnapshot:
    name: str
    kind: Literal["rgb_camera", "event_sensor", "trigger"]
    state: DeviceState
    total: int
    rate_hz: float
    lost: int
    reconnects: int
    queued: int
    last_data_age_s: float | None
    interval_jitter_us: float | None


@dataclass(slots=True)
class ActiveFault:
    code: str
    device: str | None
    message: str
    since_utc: str
    since_mono: float


@dataclass(slots=True)
class SessionSnapshot:
    """A consistent-enough view of a running session for telemetry (cheap to take)."""

    state: SessionState
    path: Path
    elapsed_s: float
    pulses: int
    pulses_total: int | None
    queue_depth: int
    queue_capacity: int
    bytes_written: int
    devices: list[DeviceSnapshot]
    faults: list[ActiveFault]
    last_flush_age_s: float | None = None
    """Seconds since the take was last flushed (what a crash now would lose); None before
    the first flush."""
    flush_max_s: float = 0.0
    """The longest flush so far (the writer's stall; fsync waits for the disk)."""


@dataclass(slots=True)
class _Observations:
    """Trigger observations kept in memory for the sync engine (small: one per pulse)."""

    t: list[int] = field(default_factory=list)
    host: list[int] = field(default_factory=list)
    counter: list[int] = field(default_factory=list)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return (
            np.asarray(self.t, np.int64),
            np.asarray(self.host, np.int64),
            np.asarray(self.counter, np.int64),
        )


@dataclass(slots=True)
class _Live:
    """Per-device counters the acquisition and writer threads update for telemetry."""

    kind: Literal["rgb_camera", "event_sensor", "trigger"]
    state: DeviceState = "ok"
    total: int = 0
    queued: int = 0
    reconnects: int = 0
    last_data_mono: float | None = None
    rate_hz: float = 0.0
    samples: deque[tuple[float, int]] = field(default_factory=lambda: deque(maxlen=128))
    """(host monotonic s, total) a few times a second, for the rate over the last 2 s."""
    last_t: int | None = None
    """Device time of the newest item delivered."""
    gap_started: tuple[float, int | None, str] | None = None
    """(host monotonic s, last device time before the gap, why) while the device is away."""


class Ballast:
    """Disk space held back while a take runs and given up the moment the disk is full, so
    the take can still be closed cleanly (an HDF5 file that cannot write its metadata on
    close is left inconsistent in memory). Stale ballast files of a killed process are
    removed by `remove_stale_ballast` when the daemon starts."""

    PREFIX = ".rigd-ballast-"

    def __init__(self, directory: Path, size_bytes: int) -> None:
        self.path = directory / f"{self.PREFIX}{uuid.uuid4().hex[:8]}"
        self.size = size_bytes
        if size_bytes <= 0:
            return
        fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
        try:
            try:
                os.posix_fallocate(fd, 0, size_bytes)
            except OSError as exc:
                if exc.errno != errno.EOPNOTSUPP:
                    raise
                block = b"\0" * (1 << 20)  # file systems without fallocate: write it out
                for _ in range(0, size_bytes, len(block)):
                    os.write(fd, block)
        except OSError as exc:
            os.close(fd)
            self.path.unlink(missing_ok=True)
            raise TakeError(
                f"cannot hold {size_bytes / 1e6:.0f} MB of ballast in {directory}: {exc.strerror} "
                "(writer.disk_ballast_mb)"
            ) from exc
        os.close(fd)

    def release(self, *, emergency: bool = False) -> None:
        """Give the space back; `emergency`: the disk is full (said as a warning)."""
        if self.size > 0 and self.path.exists():
            self.path.unlink()
            level = logging.WARNING if emergency else logging.DEBUG
            log.log(level, "released %.0f MB of disk ballast (%s)", self.size / 1e6, self.path)


def remove_stale_ballast(directory: Path) -> int:
    n = 0
    for p in directory.glob(f"{Ballast.PREFIX}*"):
        p.unlink(missing_ok=True)
        n += 1
    return n


def _utc_now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


class _Pipeline:
    """State shared by the acquisition threads, the writer thread and the control thread."""

    def __init__(self, config: RigConfig, path: Path, reconnect_interval_s: float) -> None:
        self.config = config
        self.path = path
        self.reconnect_interval_s = reconnect_interval_s
        self.queue: queue.Queue[Any] = queue.Queue(maxsize=config.writer.queue_items)
        self.stop_acq = threading.Event()
        self.stop_requested = threading.Event()
        self.stop_reason: str | None = None
        self.end_reason = ""
        self.stop_by_fault = False
        self.errors: list[BaseException] = []
        self.losses: list[LossRecord] = []
        self.lock = threading.Lock()
        self.obs: dict[str, _Observations] = {}
        self.frames: dict[str, int] = {c.name: 0 for c in config.cameras}
        self.events: dict[str, int] = {s.name: 0 for s in config.event_sensors}
        self.device_counters: dict[str, dict[str, int]] = {}
        self.failed_devices: dict[str, str] = {}
        self.trigger_channel = {s.name: s.settings.trigger_in_channel for s in config.event_sensors}
        self.clock_resets: dict[str, ClockReset] = {}
        self.pulses: list[PulseBatch] = []
        self.n_pulses = 0
        self.trigger: Trigger | None = None
        self.cameras: dict[str, RgbCamera] = {}
        self.sensors: dict[str, EventSensor] = {}
        self.threads: list[threading.Thread] = []
        self.writer: TakeWriter | None = None
        self.writer_error: OSError | None = None
        self.ballast: Ballast | None = None
        self.live: dict[str, _Live] = {"trigger": _Live("trigger")}
        self.faults: dict[tuple[str, str | None], ActiveFault] = {}
        self.fault_history: list[str] = []
        self.last_frame: dict[str, Frame] = {}
        self.last_events: dict[str, list[EventArray]] = {}
        self.last_flush_utc: str | None = None
        self.last_flush_mono: float | None = None

    # -- faults --------------------------------------------------------------------------
    def set_fault(self, code: str, device: str | None, message: str) -> None:
        with self.lock:
            if (code, device) in self.faults:
                self.faults[(code, device)].message = message
                return
            self.faults[(code, device)] = ActiveFault(code, device, message, _utc_now(), time.monotonic())
        log.error("fault %s%s: %s", code, f" ({device})" if device else "", message)

    def clear_fault(self, code: str, device: str | None) -> None:
        with self.lock:
            fault = self.faults.pop((code, device), None)
        if fault is not None:
            lasted = time.monotonic() - fault.since_mono
            self.fault_history.append(_fault_line(fault, lasted))
            log.warning("fault %s%s cleared after %.2f s", code, f" ({device})" if device else "", lasted)

    def request_stop(self, reason: str, *, fault: bool = False) -> None:
        """`fault`: the rig stopped itself (disk, trigger); the take's report says why."""
        with self.lock:
            if self.stop_reason is None:
                self.stop_reason = reason
                self.stop_by_fault = fault
        self.stop_requested.set()

    # -- devices -------------------------------------------------------------------------
    def open_devices(self) -> None:
        cfg = self.config
        self.trigger = open_device("trigger", cfg.trigger.spec)
        self.trigger.configure(cfg.trigger.settings)
        for cam in cfg.cameras:
            dev = open_device("rgb_camera", cam.spec)
            self.cameras[cam.name] = dev
            dev.configure(cam.settings)
            self.live[cam.name] = _Live("rgb_camera")
        for sen in cfg.event_sensors:
            ev = open_device("event_sensor", sen.spec)
            self.sensors[sen.name] = ev
            ev.configure(sen.settings)
            self.live[sen.name] = _Live("event_sensor")
        for name in [*self.cameras, *self.sensors]:
            self.obs[name] = _Observations()

    def close_devices(self) -> None:
        for dev in [*self.cameras.values(), *self.sensors.values(), self.trigger]:
            if dev is None:
                continue
            try:
                dev.close()
            except RigdError as exc:
                log.error("closing %s failed: %s", dev.info.spec, exc)
                self.errors.append(exc)

    def _reopen(self, name: str) -> None:
        """Open, configure and start a device again from its config entry."""
        dev: RgbCamera | EventSensor
        cam = next((c for c in self.config.cameras if c.name == name), None)
        if cam is not None:
            dev = open_device("rgb_camera", cam.spec)
            settings: Any = cam.settings
        else:
            sen = next(s for s in self.config.event_sensors if s.name == name)
            dev = open_device("event_sensor", sen.spec)
            settings = sen.settings
        try:
            dev.configure(settings)
            dev.start()
        except BaseException:
            dev.close()
            raise
        if isinstance(dev, RgbCamera):
            self.cameras[name] = dev
        else:
            self.sensors[name] = dev

    def _reconnect(self, name: str, exc: DeviceError) -> None:
        """A device failed mid-take: keep trying to open it again until it answers or the
        take ends (then it is written off with a loss record by `_guard`)."""
        live = self.live[name]
        with self.lock:
            live.state = "reconnecting"
            if live.gap_started is None:
                live.gap_started = (time.monotonic(), live.last_t, str(exc))
        self.set_fault("device_reconnecting", name, f"{name} lost ({exc}); reconnecting")
        old = self.cameras.get(name) or self.sensors.get(name)
        if old is not None:
            try:
                old.close()
            except DeviceError as close_exc:
                log.warning("closing lost device %s: %s", name, close_exc)
        if self.reconnect_interval_s <= 0:
            raise exc
        while not self.stop_acq.wait(self.reconnect_interval_s):
            try:
                self._reopen(name)
            except DeviceError as again:
                log.info("device %s still away: %s", name, again)
                continue
            with self.lock:
                live.state = "ok"
                live.reconnects += 1
            log.warning("device %s reconnected after %.1f s", name, time.monotonic() - live.gap_started[0])
            self.clear_fault("device_reconnecting", name)
            return
        self.clear_fault("device_reconnecting", name)
        raise DeviceError(f"{name} did not come back before the end of the take (lost: {exc})") from exc

    def _deliver(self, name: str, kind: str, item: Any) -> None:
        """One frame or event packet from a device, on its way to the writer; a device that
        came back with its clock restarted is re-tied onto its old clock first."""
        reset = self.clock_resets.get(name)
        if (t_before := self._restarted(name, kind, item, reset)) is not None:
            reset = self.clock_resets[name] = ClockReset(
                name,
                "rgb_camera" if kind == "frame" else "event_sensor",
                t_before,
                self.trigger_channel.get(name, 0),
            )
            log.warning("%s came back with its clock restarted; tying it to its old clock", name)
        if reset is None:
            self._pass(name, kind, item)
            return
        if reset.offset is not None:
            self._pass(name, kind, reset.shift(kind, item))
            return
        seen = len(reset.post_t)
        reset.hold(kind, item)
        if len(reset.post_t) == seen and reset.held_for_s() <= MAX_HOLD_S:
            return  # nothing new to tie with (an event packet without trigger edges)
        if not self._tie(reset):
            return
        for held_kind, held in reset.release():
            self._pass(name, held_kind, held)

    def _restarted(self, name: str, kind: str, item: Any, reset: ClockReset | None) -> int | None:
        """For a first delivery after a reconnect whose time lies before the last one before
        the gap: that last time (the device's clock restarted); else None. A device already
        re-tied is compared on its old clock (it may restart again); one still being tied is
        not asked (its gap stays open until it is)."""
        gap = self.live[name].gap_started
        t = _first_time(kind, item)
        if reset is not None:
            if reset.offset is None:
                return None
            t = None if t is None else t + reset.offset.us
        if gap is None or gap[1] is None or t is None or t >= gap[1]:
            return None
        return gap[1]

    def _tie(self, reset: ClockReset) -> bool:
        """Try to place the restarted clock on the old one; True once done. A device that does
        not tie within MAX_OBSERVATIONS is written off (what was held is counted lost)."""
        pre_t, pre_host, _ = self.obs[reset.name].arrays()
        n = min(pre_t.size, pre_host.size)
        with self.lock:
            pulses = pulse_log(self.pulses, 0)
        period_us = 1e6 / self.config.trigger.settings.rate_hz
        offset = estimate_offset(reset, pre_t[:n], pre_host[:n], pulses, period_us)
        if offset is None:
            if len(reset.post_t) >= MAX_OBSERVATIONS or reset.held_for_s() > MAX_HOLD_S:
                self._drop_held(reset.name, "its restarted clock could not be tied to the trigger pulses")
                self._stop_written_off(reset.name)
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
        with self.lock:
            self.fault_history.append(line)
        return True

    def _stop_written_off(self, name: str) -> None:
        """A live device about to be written off stops acquiring (bus bandwidth, its buffers)."""
        dev = self.cameras.get(name) or self.sensors.get(name)
        if dev is None:
            return
        try:
            dev.stop()
        except DeviceError as exc:
            log.warning("stopping %s before writing it off: %s", name, exc)

    def _drop_held(self, name: str, why: str) -> None:
        reset = self.clock_resets.get(name)
        if reset is None or not reset.held:
            return
        count = reset.held_count()
        kind = reset.held[0][0]
        reset.held.clear()
        with self.lock:
            self.losses.append(
                LossRecord(
                    device=name, what=_what(kind), count=count, reason=f"held back and not written: {why}"
                )
            )

    def _pass(self, name: str, kind: str, item: Any) -> None:
        if kind == "frame":
            t = item.t_exposure_start_us
            self._arrived(name, "frames", t)
            self._put(name, "frames", ("frame", name, item), (t, t), 1)
            return
        ev = item.events
        t_range = (int(ev.t[0]), int(ev.t[-1])) if len(ev) else None
        self._arrived(name, "events", _first_time(kind, item), t_range[1] if t_range else None)
        self._put(name, "events", ("events", name, item), t_range, len(ev))

    def _arrived(self, name: str, what: LossKind, t_device: int | None, t_last: int | None = None) -> None:
        """Bookkeeping for one delivery; closes a reconnect gap with its loss record."""
        live = self.live[name]
        live.last_data_mono = time.monotonic()
        if t_device is None:
            return
        gap = live.gap_started
        if gap is not None:
            since, t_before, why = gap
            if t_before is not None and t_device < t_before:
                raise DeviceError(
                    f"{name} came back with its clock reset ({t_device} us after {t_before} us) and "
                    "was tied wrongly; written off from here"
                )
            away = time.monotonic() - since
            with self.lock:
                live.gap_started = None
                self.losses.append(
                    LossRecord(
                        device=name,
                        what=what,
                        count=0,
                        reason=f"device away for {away:.2f} s ({why}); reconnected, nothing recorded in "
                        "between (count unknown: see t_first_us..t_last_us and the sync report)",
                        t_first_us=t_before,
                        t_last_us=t_device,
                    )
                )
        live.last_t = t_device if t_last is None else t_last

    # -- acquisition threads -------------------------------------------------------------
    def _put(
        self, device: str, what: LossKind, item: Any, t_range: tuple[int, int] | None, count: int
    ) -> None:
        live = self.live[device]
        with self.lock:
            live.queued += 1
        try:
            self.queue.put(item, timeout=self.config.writer.queue_put_timeout_s)
        except queue.Full:
            log.warning("writer queue full: %d %s of %s lost", count, what, device)
            self.set_fault("queue_full", None, "the writer cannot keep up; data is being dropped (counted)")
            with self.lock:
                live.queued -= 1
                self.losses.append(
                    LossRecord(
                        device=device,
                        what=what,
                        count=count,
                        reason="writer queue full (host could not keep up)",
                        t_first_us=t_range[0] if t_range else None,
                        t_last_us=t_range[1] if t_range else None,
                    )
                )
            return
        if ("queue_full", None) in self.faults and self.queue.qsize() < self.queue.maxsize // 2:
            self.clear_fault("queue_full", None)  # the writer caught up

    def _guard(self, name: str, fn: Callable[[], None], device: str | None = None) -> Callable[[], None]:
        """Run a thread body; an error ends the capture, except a camera or event sensor that
        fails for good (unplugged and not back, say): that device is written off with a loss
        record and the take goes on with the others."""

        def run() -> None:
            try:
                fn()
            except DeviceError as exc:
                if device is None:
                    log.exception("acquisition thread %s failed", name)
                    with self.lock:
                        self.errors.append(exc)
                    self.stop_acq.set()
                    return
                log.error("device %s failed mid-take, the others go on: %s", device, exc)
                self.set_fault("device_failed", device, f"{device} written off: {exc}")
                with self.lock:
                    self.live[device].state = "failed"
                    self.failed_devices[device] = str(exc)
                    self.losses.append(
                        LossRecord(
                            device=device,
                            what="frames" if device in self.cameras else "events",
                            count=0,
                            reason=f"device failed mid-take; no data after this point: {exc}",
                            t_first_us=self.live[device].last_t,
                        )
                    )
            except BaseException as exc:  # recorded and re-raised by the control thread
                log.exception("acquisition thread %s failed", name)
                with self.lock:
                    self.errors.append(exc)
                self.stop_acq.set()

        return run

    def _device_loop(self, name: str, kind: Literal["frame", "events"]) -> None:
        """Read a camera's frames or a sensor's event packets until the take ends; the device
        object is looked up on every read because a reconnect replaces it."""
        while True:
            try:
                if kind == "frame":
                    item: Frame | EventPacket | None = self.cameras[name].read_frame(_READ_TIMEOUT_S)
                else:
                    item = self.sensors[name].read_events(_READ_TIMEOUT_S)
            except DeviceError as exc:
                if self.stop_acq.is_set():
                    raise
                self._reconnect(name, exc)
                continue
            if item is None:
                if self.stop_acq.is_set():
                    self._drop_held(name, "the take ended before its restarted clock could be tied")
                    return
                continue
            self._deliver(name, kind, item)

    def _trigger_loop(self, trigger: Trigger) -> None:
        live = self.live["trigger"]
        while True:
            batch = trigger.read_pulses(_READ_TIMEOUT_S)
            if len(batch):
                with self.lock:
                    self.pulses.append(batch)
                    self.n_pulses += len(batch)
                    live.total = self.n_pulses
                live.last_data_mono = time.monotonic()
                self._put("trigger", "pulses", ("pulses", "trigger", batch), None, len(batch))
            elif self.stop_acq.is_set():
                return

    def start_threads(self) -> None:
        assert self.trigger is not None
        targets: list[tuple[str, Callable[[], None], str | None]] = [
            (f"acq-{n}", functools.partial(self._device_loop, n, "frame"), n) for n in self.cameras
        ]
        targets += [(f"acq-{n}", functools.partial(self._device_loop, n, "events"), n) for n in self.sensors]
        targets.append(("acq-trigger", functools.partial(self._trigger_loop, self.trigger), None))
        for name, fn, device in targets:
            th = threading.Thread(target=self._guard(name, fn, device), name=name, daemon=True)
            th.start()
            self.threads.append(th)

    # -- writer thread -------------------------------------------------------------------
    def writer_loop(self) -> None:
        writer = self.writer
        assert writer is not None
        interval = self.config.writer.flush_interval_s
        last_flush = time.monotonic()
        while True:
            try:
                item = self.queue.get(timeout=min(0.2, interval / 2))
            except queue.Empty:
                item = None
            if item is _STOP:
                if self.writer_error is None:
                    self._flush(writer)
                return
            if item is not None:
                kind, name, payload = item
                with self.lock:
                    self.live[name].queued -= 1
                if self.writer_error is not None:
                    self._refused(name, kind, payload, f"not written: the take stopped ({self.writer_error})")
                    continue
                try:
                    self._write(writer, kind, name, payload)
                except TakeError as exc:
                    # Bad data from one device must not cost the rest of the take.
                    log.error("refused data from %s: %s", name, exc)
                    self._refused(name, kind, payload, str(exc))
                except OSError as exc:
                    self._writer_failed(exc)
                    self._refused(name, kind, payload, f"not written: {exc}")
                    continue
            now = time.monotonic()
            if self.writer_error is None and now - last_flush >= interval:
                try:
                    self._flush(writer)
                except OSError as exc:
                    self._writer_failed(exc)
                last_flush = now

    def _flush(self, writer: TakeWriter) -> None:
        writer.flush(journal=self.journal())
        self.last_flush_utc = _utc_now()
        self.last_flush_mono = time.monotonic()

    def _refused(self, name: str, kind: str, payload: Any, reason: str) -> None:
        with self.lock:
            self.losses.append(
                LossRecord(device=name, what=_what(kind), count=_count(payload), reason=reason)
            )

    def _writer_failed(self, exc: OSError) -> None:
        """The file system refused a write (disk full, I/O error): stop the take cleanly.

        Everything flushed before stays in the file; what comes after is counted as lost."""
        self.writer_error = exc
        if self.ballast is not None:
            self.ballast.release(emergency=True)  # room to close the take cleanly
        full = exc.errno == errno.ENOSPC or "No space left" in str(exc)
        code = "disk_full" if full else "writer_failed"
        self.set_fault(code, None, f"writing {self.path.name} failed: {exc}")
        self.request_stop(f"{'disk full' if full else 'write error'}: {exc}", fault=True)

    def _write(self, writer: TakeWriter, kind: str, name: str, payload: Any) -> None:
        """Write one item; observations are kept only for what reached the file, so the
        sync engine's per-frame pulse indices line up with the written frames."""
        if kind == "frame":
            frame: Frame = payload
            writer.append_frame(name, frame)
            obs = self.obs[name]
            obs.t.append(frame.t_exposure_start_us)
            obs.host.append(frame.host_time_ns)
            obs.counter.append(frame.frame_counter)
            self.frames[name] += 1
            self.live[name].total += 1
            self.last_frame[name] = frame
        elif kind == "events":
            packet: EventPacket = payload
            if len(packet.events):
                writer.append_events(name, packet.events)
                recent = self.last_events.setdefault(name, [])
                recent.append(packet.events)
                del recent[:-8]
            if len(packet.triggers):
                writer.append_triggers(name, packet.triggers, packet.host_time_ns)
                rising = packet.triggers.rising(self.trigger_channel[name])
                obs = self.obs[name]
                obs.t.extend(rising.t.tolist())
                obs.host.extend([packet.host_time_ns] * len(rising))
            self.events[name] += len(packet.events)
            self.live[name].total += len(packet.events)
        elif kind == "pulses":
            writer.append_pulses(payload)

    def journal(self) -> dict[str, Any]:
        """What the take must not lose if the process dies: the loss bookkeeping so far."""
        with self.lock:
            return {
                "losses": [r.model_dump() for r in self.losses],
                "failed_devices": dict(self.failed_devices),
                "device_counters": {k: dict(v) for k, v in self.device_counters.items()},
                "faults": [_fault_line(f, time.monotonic() - f.since_mono) for f in self.faults.values()],
                "fault_history": list(self.fault_history),
                "trigger_link": self.trigger.link_stats() if self.trigger is not None else {},
            }

    def progress(self, n_total: int) -> Progress:
        with self.lock:
            n = self.n_pulses
        return Progress(n, n_total, dict(self.frames), dict(self.events), self.queue.qsize())

    # -- watchdogs and telemetry ---------------------------------------------------------
    def update_rates(self) -> None:
        """Rates over the last ~2 s (sliding, so batched deliveries do not make them jump)."""
        now = time.monotonic()
        for live in self.live.values():
            samples = live.samples
            if not samples or now - samples[-1][0] >= 0.1:
                samples.append((now, live.total))
            while len(samples) > 2 and now - samples[1][0] >= _RATE_WINDOW_S:
                samples.popleft()
            t0, n0 = samples[0]
            if now - t0 >= 0.3:
                live.rate_hz = (live.total - n0) / (now - t0)

    def interval_jitter_us(self, name: str) -> float | None:
        obs = self.obs.get(name)
        if obs is None:
            return None
        t = np.asarray(obs.t[-_JITTER_WINDOW - 1 :], np.int64)
        if t.size < 3:
            return None
        period = 1e6 / self.config.trigger.settings.rate_hz
        d = np.diff(t).astype(np.float64)
        m = np.maximum(np.rint(d / period), 1.0)
        return float(np.std(d - m * period))

    def device_snapshots(self) -> list[DeviceSnapshot]:
        now = time.monotonic()
        lost: dict[str, int] = {}
        with self.lock:
            for r in self.losses:
                lost[r.device] = lost.get(r.device, 0) + r.count
        out = []
        for name, live in self.live.items():
            age = None if live.last_data_mono is None else now - live.last_data_mono
            out.append(
                DeviceSnapshot(
                    name,
                    live.kind,
                    live.state,
                    live.total,
                    live.rate_hz,
                    lost.get(name, 0),
                    live.reconnects,
                    live.queued,
                    age,
                    None if live.kind == "trigger" else self.interval_jitter_us(name),
                )
            )
        return out


class _TriggerWatchdog:
    """Says within a second when the trigger link goes quiet or carries only garbage.

    Watches the driver's line counters; at rates too slow for the pulse records themselves
    to show silence in time, it asks the box for its count (a reply is a line)."""

    def __init__(self, pipe: _Pipeline) -> None:
        self.pipe = pipe
        self.period_s = 1.0 / pipe.config.trigger.settings.rate_hz
        self.threshold_s = (
            max(_TRIGGER_SILENT_S, 2.5 * self.period_s) if self.period_s < 0.2 else _TRIGGER_SILENT_S
        )
        self.lines = -1
        self.corrupt = 0
        self.line_mono = time.monotonic()
        self.corrupt_mono = 0.0
        self.probe: threading.Thread | None = None
        self.probe_failed: str | None = None

    def check(self) -> None:
        pipe = self.pipe
        if pipe.trigger is None:
            return
        stats = pipe.trigger.link_stats()
        now = time.monotonic()
        lines, corrupt = int(stats.get("lines", 0)), int(stats.get("corrupt_lines", 0))
        if lines != self.lines:
            self.lines, self.line_mono = lines, now
            self.probe_failed = None
            pipe.clear_fault("trigger_silent", "trigger")
            pipe.clear_fault("trigger_garbage", "trigger")
        if corrupt != self.corrupt:
            self.corrupt, self.corrupt_mono = corrupt, now
        quiet = now - self.line_mono
        if quiet < self.threshold_s:
            return
        if self.corrupt_mono > self.line_mono:
            pipe.set_fault(
                "trigger_garbage",
                "trigger",
                f"the trigger link carries only garbage: {corrupt} corrupt lines so far, no valid line "
                f"for {quiet:.1f} s",
            )
            return
        if self.period_s * 2.5 <= self.threshold_s or self.probe_failed is not None:
            why = f" ({self.probe_failed})" if self.probe_failed else ""
            pipe.set_fault(
                "trigger_silent",
                "trigger",
                f"no line from the trigger box for {quiet:.1f} s (a pulse record was due every "
                f"{self.period_s * 1e3:.0f} ms){why}",
            )
        elif self.probe is None or not self.probe.is_alive():
            self.probe = threading.Thread(target=self._probe, name="trigger-probe", daemon=True)
            self.probe.start()

    def _probe(self) -> None:
        assert self.pipe.trigger is not None
        try:
            self.pipe.trigger.pulse_count()
        except DeviceError as exc:
            self.probe_failed = f"COUNT? unanswered: {exc}"


def _fault_line(fault: ActiveFault, lasted_s: float) -> str:
    where = f" on {fault.device}" if fault.device else ""
    return f"fault {fault.code}{where} from {fault.since_utc} for {lasted_s:.2f} s: {fault.message}"


def _what(kind: str) -> LossKind:
    kinds: dict[str, LossKind] = {"frame": "frames", "events": "events", "pulses": "pulses"}
    return kinds[kind]


def _count(payload: Any) -> int:
    if isinstance(payload, Frame):
        return 1
    if isinstance(payload, EventPacket):
        return len(payload.events)
    return len(payload)


def new_take_path(out_dir: Path, rig_name: str, label: str | None = None) -> Path:
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    middle = f"-{label}" if label else ""
    return out_dir / f"{rig_name}{middle}-{stamp}-{uuid.uuid4().hex[:6]}.h5"


DiskUsage = Callable[[Path], "shutil._ntuple_diskusage"]


class CaptureSession:
    """One take, run in the background: start, watch, stop, collect the result.

    `duration_s=None` runs until `request_stop`. The session stops by itself, and still
    finalizes what it has, when the disk runs low (free space under
    `writer.disk_reserve_mb`) or the file system refuses a write; it reconnects a camera or
    event sensor that disappears (every `reconnect_interval_s`; 0 writes it off at once).
    """

    def __init__(
        self,
        config: RigConfig,
        out_dir: Path,
        *,
        duration_s: float | None = None,
        path: Path | None = None,
        label: str | None = None,
        reconnect_interval_s: float = 1.0,
        disk_usage: DiskUsage = shutil.disk_usage,
    ) -> None:
        if duration_s is not None and duration_s <= 0:
            raise RigdError(f"duration must be positive, got {duration_s}")
        self.config = config
        self.rate = config.trigger.settings.rate_hz
        self.n_pulses = None if duration_s is None else max(1, round(duration_s * self.rate))
        self.out_dir = out_dir
        self.path = path or new_take_path(out_dir, config.name, label)
        self._disk_usage = disk_usage
        self._pipe = _Pipeline(config, self.path, reconnect_interval_s)
        self._state: SessionState = "new"
        self._t_wall = 0.0
        self._t_start: float | None = None
        self._writer_thread: threading.Thread | None = None
        self._control: threading.Thread | None = None
        self._result: CaptureResult | None = None
        self._error: BaseException | None = None
        self._done = threading.Event()
        self._watchdog = _TriggerWatchdog(self._pipe)

    # -- public API ----------------------------------------------------------------------
    @property
    def state(self) -> SessionState:
        return self._state

    def start(self) -> Path:
        """Open the devices, create the take and start the trigger; errors raise here."""
        if self._state != "new":
            raise RigdError("a capture session can only be started once")
        self._state = "starting"
        self._t_wall = time.monotonic()
        pipe = self._pipe
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            self._check_disk(preflight=True)
            pipe.ballast = Ballast(self.out_dir, self.config.writer.disk_ballast_mb * 1_000_000)
            self._open()
        except BaseException as exc:
            self._abort(exc)
            self._state = "failed"
            self._error = exc
            self._done.set()
            raise
        log.info(
            "capturing %s pulses at %.3f Hz into %s",
            self.n_pulses if self.n_pulses is not None else "until stopped:",
            self.rate,
            pipe.path,
        )
        self._state = "capturing"
        self._control = threading.Thread(target=self._run, name="capture-control", daemon=True)
        self._control.start()
        return self.path

    def request_stop(self, reason: str = "stop requested") -> None:
        """Stop after the current pulse; the take is finalized as usual."""
        self._pipe.request_stop(reason)

    def wait(self, timeout: float | None = None) -> CaptureResult | None:
        """The result once done (None on timeout); re-raises what ended the take."""
        if not self._done.wait(timeout):
            return None
        if self._error is not None:
            raise self._error
        return self._result

    @property
    def done(self) -> bool:
        return self._done.is_set()

    @property
    def error(self) -> BaseException | None:
        return self._error

    @property
    def result(self) -> CaptureResult | None:
        return self._result

    def progress(self) -> Progress:
        return self._pipe.progress(self.n_pulses or 0)

    def snapshot(self) -> SessionSnapshot:
        pipe = self._pipe
        pipe.update_rates()
        with pipe.lock:
            faults = list(pipe.faults.values())
        try:
            size = self.path.stat().st_size
        except OSError:
            size = 0
        return SessionSnapshot(
            self._state,
            self.path,
            0.0 if self._t_start is None else time.monotonic() - self._t_start,
            pipe.n_pulses,
            self.n_pulses,
            pipe.queue.qsize(),
            pipe.queue.maxsize,
            size,
            pipe.device_snapshots(),
            faults,
            None if pipe.last_flush_mono is None else time.monotonic() - pipe.last_flush_mono,
            0.0 if pipe.writer is None else pipe.writer.flush_seconds_max,
        )

    def latest_frames(self) -> dict[str, Frame]:
        return dict(self._pipe.last_frame)

    def latest_events(self) -> dict[str, tuple[EventArray, tuple[int, int]]]:
        out = {}
        for name, parts in list(self._pipe.last_events.items()):
            if parts and name in self._pipe.sensors:
                out[name] = (EventArray.concatenate(list(parts)), self._pipe.sensors[name].geometry)
        return out

    # -- internals -----------------------------------------------------------------------
    def _open(self) -> None:
        pipe, config = self._pipe, self.config
        pipe.open_devices()
        assert pipe.trigger is not None
        writer = TakeWriter(
            self.path,
            rig_config_json=config.model_dump_json(),
            take_id=self.path.stem,
            config=config.writer,
            rigd_version=__version__,
            flush_interval_s=config.writer.flush_interval_s,
        )
        pipe.writer = writer
        writer.add_trigger(pipe.trigger.info)
        for cam_cfg in config.cameras:
            cam = pipe.cameras[cam_cfg.name]
            writer.add_camera(
                cam_cfg.name, cam.info, cam.frame_shape, cam.frame_dtype, cam_cfg.settings.model_dump_json()
            )
        for sen_cfg in config.event_sensors:
            sen = pipe.sensors[sen_cfg.name]
            w, h = sen.geometry
            writer.add_event_sensor(sen_cfg.name, sen.info, w, h, sen_cfg.settings.model_dump_json())
        self._writer_thread = threading.Thread(target=pipe._guard("writer", pipe.writer_loop), name="writer")
        self._writer_thread.start()
        pipe.start_threads()
        for cam in pipe.cameras.values():
            cam.start()
        for sen in pipe.sensors.values():
            sen.start()
        pipe.trigger.arm()
        self._t_start = time.monotonic()
        pipe.trigger.start(self.n_pulses)
        self._watchdog.line_mono = time.monotonic()
        for live in pipe.live.values():
            live.samples.clear()

    def _check_flushes(self, now: float) -> None:
        """A writer that stopped flushing (a hung disk or network mount) puts everything since
        at risk: say so long before the queue fills."""
        pipe = self._pipe
        if pipe.writer_error is not None or self._t_start is None:
            return
        interval = self.config.writer.flush_interval_s
        since = self._t_start if pipe.last_flush_mono is None else pipe.last_flush_mono
        if now - since > max(3 * interval, interval + FLUSH_STALL_SLACK_S):
            pipe.set_fault(
                "writer_stalled",
                None,
                f"no flush for {now - since:.1f} s (every {interval:g} s expected): the disk is not "
                "taking writes; a crash now would lose everything since",
            )
        else:
            pipe.clear_fault("writer_stalled", None)

    def _check_disk(self, *, preflight: bool = False) -> None:
        reserve = self.config.writer.disk_reserve_mb * 1_000_000
        free = self._disk_usage(self.out_dir).free
        if free >= reserve:
            self._pipe.clear_fault("disk_low", None)
            return
        msg = f"{free / 1e6:.0f} MB free in {self.out_dir}, below the reserve of {reserve / 1e6:.0f} MB"
        if preflight:
            raise TakeError(f"not starting a take: {msg} (writer.disk_reserve_mb)")
        self._pipe.set_fault("disk_low", None, msg)
        self._pipe.request_stop(f"disk space low: {msg}", fault=True)

    def _run(self) -> None:
        pipe = self._pipe
        try:
            self._watch()
            self._state = "stopping"
            self._result = self._finish()
            self._state = "done"
        except BaseException as exc:  # noqa: BLE001 - kept and re-raised by wait()
            log.error("take %s failed: %s: %s", self.path, type(exc).__name__, exc)
            self._error = exc
            self._state = "failed"
            self._abort(exc)
        finally:
            self._close_take()
            pipe.close_devices()
            self._done.set()

    def _close_take(self) -> None:
        pipe = self._pipe
        try:
            if pipe.writer is not None:
                try:
                    pipe.writer.close()
                except OSError as exc:  # what was flushed stays on disk
                    log.error("closing take %s: %s", self.path, exc)
        finally:
            if pipe.ballast is not None:
                pipe.ballast.release()

    def _watch(self) -> None:
        """Until the pulses are out, a stop is asked for or something fatal happens."""
        pipe = self._pipe
        assert pipe.trigger is not None
        deadline = None if self.n_pulses is None else time.monotonic() + self.n_pulses / self.rate * 1.5 + 5.0
        next_disk = 0.0
        while True:
            if pipe.errors:
                raise pipe.errors[0]
            if pipe.stop_requested.is_set():
                log.info("stopping take %s: %s", self.path, pipe.stop_reason)
                return
            if self.n_pulses is not None and pipe.n_pulses >= self.n_pulses:
                return
            now = time.monotonic()
            if self.n_pulses is None or pipe.n_pulses < self.n_pulses:
                self._watchdog.check()
            if now >= next_disk:
                self._check_disk()
                self._check_flushes(now)
                next_disk = now + 1.0
            if deadline is not None and now > deadline:
                msg = f"the trigger delivered {pipe.n_pulses} of {self.n_pulses} pulse records in time"
                log.error("take %s: %s; finalizing what there is", self.path, msg)
                pipe.request_stop(msg, fault=True)
                return
            time.sleep(0.05)

    def _stop_trigger(self) -> int:
        pipe = self._pipe
        assert pipe.trigger is not None
        try:
            return pipe.trigger.stop()
        except DeviceError as exc:
            with pipe.lock:
                seen = max((int(b.index.max()) + 1 for b in pipe.pulses if len(b)), default=0)
            pipe.fault_history.append(f"the trigger box did not confirm STOP ({exc}); {seen} pulses assumed")
            log.error("trigger STOP failed (%s); assuming %d pulses", exc, seen)
            return seen

    def _finish(self) -> CaptureResult:
        pipe = self._pipe
        assert self._writer_thread is not None
        assert self._t_start is not None
        emitted = self._stop_trigger()
        # Let the last exposures and event slices reach the host before stopping devices.
        _drain_wait(pipe, self.rate)
        devices: dict[str, RgbCamera | EventSensor] = {**pipe.sensors, **pipe.cameras}
        for name, dev in devices.items():
            _stop_device(pipe, name, dev)
        pipe.stop_acq.set()
        for th in pipe.threads:
            th.join()
        _record_device_losses(pipe)
        pipe.queue.put(_STOP)
        self._writer_thread.join()
        self._writer_thread = None
        capture_s = time.monotonic() - self._t_start
        assert pipe.writer is not None
        writer_flushes, writer_flush_max_s = pipe.writer.flush_count, pipe.writer.flush_seconds_max
        if pipe.errors:
            raise pipe.errors[0]
        if pipe.writer_error is not None:
            raise TakeError(
                f"take {self.path} stopped, {pipe.stop_reason}; everything up to the last flush "
                f"({pipe.last_flush_utc}) is in the file; free space and run `rigd recover` to seal it"
            )
        report = _finalize(pipe, emitted, self.rate)
        return CaptureResult(
            self.path,
            report,
            dict(pipe.frames),
            dict(pipe.events),
            self.path.stat().st_size,
            time.monotonic() - self._t_wall,
            capture_s,
            flushes=writer_flushes,
            flush_max_s=writer_flush_max_s,
            end_reason=pipe.end_reason,
        )

    def _abort(self, exc: BaseException) -> None:
        pipe = self._pipe
        pipe.stop_acq.set()
        if pipe.trigger is not None:
            try:
                pipe.trigger.stop()
            except RigdError as stop_exc:
                log.error("could not stop the trigger: %s", stop_exc)
        for th in pipe.threads:
            th.join(timeout=5)
        if self._writer_thread is not None:
            pipe.queue.put(_STOP)
            self._writer_thread.join(timeout=30)
        if pipe.writer is not None:
            # Everything written so far stays in the file, marked failed with the reason
            # (after a full disk, in the room the released ballast made).
            try:
                pipe.writer.fail(f"{type(exc).__name__}: {exc}")
            except (OSError, TakeError) as fail_exc:
                log.error("could not mark take %s failed: %s", self.path, fail_exc)
        if self._control is None or threading.current_thread() is not self._control:
            self._close_take()
            pipe.close_devices()


def run_capture(
    config: RigConfig,
    out_dir: Path,
    duration_s: float,
    *,
    on_progress: Callable[[Progress], None] | None = None,
    path: Path | None = None,
    label: str | None = None,
    reconnect_interval_s: float = 0.5,
) -> CaptureResult:
    """Capture one take of `duration_s` seconds of trigger pulses and return its summary."""
    session = CaptureSession(
        config,
        out_dir,
        duration_s=duration_s,
        path=path,
        label=label,
        reconnect_interval_s=reconnect_interval_s,
    )
    session.start()
    try:
        while (result := session.wait(0.05)) is None:
            if on_progress:
                on_progress(session.progress())
    except KeyboardInterrupt:
        session.request_stop("interrupted")
        session.wait()
        raise
    if on_progress:
        on_progress(session.progress())
    return result


def _stop_device(pipe: _Pipeline, name: str, dev: RgbCamera | EventSensor) -> None:
    if pipe.live[name].state != "ok":
        return  # away or written off: its acquisition thread ends it
    try:
        dev.stop()
    except DeviceError as exc:
        if name not in pipe.failed_devices:
            raise
        log.warning("stopping failed device %s: %s", name, exc)


def _drain_wait(pipe: _Pipeline, rate: float) -> None:
    """Wait until every device has data past the last pulse, or a bounded grace period."""
    deadline = time.monotonic() + max(0.5, 5.0 / rate)
    while time.monotonic() < deadline and not pipe.errors:
        time.sleep(0.02)


def _record_device_losses(pipe: _Pipeline) -> None:
    """Turn device-side counters into loss records: what the device lost, what the host's
    decoder had to skip, and trigger edges that could not be delivered in order."""
    devices: dict[str, RgbCamera | EventSensor] = {**pipe.cameras, **pipe.sensors}
    for name, dev in devices.items():
        try:
            stats = dev.stats()
        except DeviceError as exc:
            if name not in pipe.failed_devices:
                raise
            log.warning("no counters from failed device %s: %s", name, exc)
            continue
        pipe.device_counters[name] = {
            "delivered": stats.delivered,
            "device_dropped": stats.device_dropped,
            **stats.extra,
        }
        is_cam = name in pipe.cameras
        if stats.device_dropped:
            pipe.losses.append(
                LossRecord(
                    device=name,
                    what="frames" if is_cam else "events",
                    count=stats.device_dropped,
                    reason="lost inside the device or its transport (device counters)",
                )
            )
        prefix = "decoder_skipped_"
        skipped = {k.removeprefix(prefix): v for k, v in stats.extra.items() if k.startswith(prefix) and v}
        if skipped:
            pipe.losses.append(
                LossRecord(
                    device=name,
                    what="events",
                    count=sum(skipped.values()),
                    reason=f"EVT decoder skipped invalid data: {skipped}",
                )
            )
        if stats.extra.get("triggers_ignored"):
            pipe.losses.append(
                LossRecord(
                    device=name,
                    what="frames",
                    count=stats.extra["triggers_ignored"],
                    reason="trigger edges arrived while the camera was busy (slower than the trigger)",
                )
            )
        if stats.extra.get("triggers_late"):
            pipe.losses.append(
                LossRecord(
                    device=name,
                    what="triggers",
                    count=stats.extra["triggers_late"],
                    reason="trigger edges arrived after their part of the stream was sent",
                )
            )


def pulse_log(batches: list[PulseBatch], emitted: int) -> PulseLog:
    """The box's pulse records so far, one per index (a re-read after a gap may repeat some)."""
    index = np.concatenate([b.index for b in batches]) if batches else np.empty(0, np.int64)
    order = np.argsort(index, kind="stable")
    uniq = np.concatenate([[True], np.diff(index[order]) > 0]) if index.size else np.empty(0, bool)
    sel = order[uniq]
    return PulseLog(
        index[sel],
        (np.concatenate([b.t_us for b in batches]) if batches else np.empty(0, np.int64))[sel],
        (np.concatenate([b.host_time_ns for b in batches]) if batches else np.empty(0, np.int64))[sel],
        max(emitted, int(index.max(initial=-1)) + 1),
    )


def _first_time(kind: str, item: Any) -> int | None:
    """Device time of the first thing in a frame or event packet."""
    if kind == "frame":
        return int(item.t_exposure_start_us)
    if len(item.events):
        return int(item.events.t[0])
    return int(item.triggers.t[0]) if len(item.triggers) else None


def _finalize(pipe: _Pipeline, emitted: int, rate: float) -> SyncReport:
    assert pipe.writer is not None
    pulses = pulse_log(pipe.pulses, emitted)
    observations = []
    for name in [*pipe.cameras, *pipe.sensors]:
        t, host, counter = pipe.obs[name].arrays()
        is_cam = name in pipe.cameras
        observations.append(
            DeviceObservations(
                name, "rgb_camera" if is_cam else "event_sensor", t, host, counter if is_cam else None
            )
        )
    slaves = {
        s.name: s.settings.sync_master
        for s in pipe.config.event_sensors
        if s.settings.sync_mode == "slave" and s.settings.sync_master is not None
    }
    software = {name for name, cam in pipe.cameras.items() if cam.info.facts.get("sync") == "software"}
    result = synchronize(
        pulses, observations, rate, pipe.losses, shares_clock_with=slaves, software_synced=software
    )
    result.report.device_counters = pipe.device_counters
    for name, why in pipe.failed_devices.items():
        result.report.warnings.append(f"{name} failed mid-take and was written off: {why}")
    with pipe.lock:
        active = [_fault_line(f, time.monotonic() - f.since_mono) for f in pipe.faults.values()]
    result.report.warnings.extend(
        [*pipe.fault_history, *(f"{line} (still active at the end)" for line in active)]
    )
    if pipe.stop_by_fault:
        result.report.warnings.append(f"the rig stopped the take itself: {pipe.stop_reason}")
        pipe.end_reason = f"stopped by the rig: {pipe.stop_reason}"
    elif pipe.stop_reason is not None:
        pipe.end_reason = f"stopped: {pipe.stop_reason}"
    else:
        pipe.end_reason = f"all {emitted} pulses done"
    pipe.writer.set_end_reason(pipe.end_reason)
    if pipe.trigger is not None:
        result.report.trigger_link = pipe.trigger.link_stats()
    frame_index = {name: result.observation_pulse_index[name] for name in pipe.cameras}
    pipe.writer.finalize(result.maps, frame_index, result.report)
    log.info("take %s finalized: %s", pipe.path, json.dumps(pipe.frames))
    return result.report
