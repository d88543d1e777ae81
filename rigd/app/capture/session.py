"""One take from start to sealed file: `CaptureSession` (background, stoppable, watched); the
blocking `run_capture` is in `run`.

The session opens every device through its channel, refuses a rig that cannot do what its
config asks (`preflight`), starts the writer thread and one acquisition thread per device,
then watches: the trigger link, the disk, the flushes. After the last pulse (or a stop) it
waits, for at most `writer.stop_backlog_s`, until every device has delivered up to the end of
the take's trigger window (`window`), stops the devices, reads what they still hold (again
bounded), fits every device clock and seals the take (`finalize`). What a device delivers
outside the window is counted, not written.
"""

from __future__ import annotations

import logging
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from drivers.base import Trigger
from rigd import __version__
from rigd.app.capture.ballast import Ballast, remove_stale_ballast
from rigd.app.capture.channel import ChannelContext, DeviceChannel, TriggerChannel
from rigd.app.capture.control import BoundedCalls, RunControl
from rigd.app.capture.faults import DiskUsage, DiskWatch, FaultBoard, FlushWatch, TriggerWatchdog
from rigd.app.capture.finalize import finalize_take
from rigd.app.capture.items import WriterQueue
from rigd.app.capture.kinds import open_channels
from rigd.app.capture.ledger import LossLedger
from rigd.app.capture.live import LiveStats
from rigd.app.capture.preflight import prepare_rig
from rigd.app.capture.remote_trigger import FeedState, RemoteTrigger
from rigd.app.capture.request import check_duration, check_out_dir, new_take_path
from rigd.app.capture.results import CaptureResult, Phase, Progress, SessionSnapshot, SessionState
from rigd.app.capture.stop import CLOSE_BOUND_S, AcquisitionStop, StopWait
from rigd.app.capture.streams import writer_streams
from rigd.app.capture.truth import store_ground_truth
from rigd.app.capture.window import TakeWindow
from rigd.app.capture.writer_loop import WriterLoop
from rigd.app.config import RigConfig
from rigd.core.errors import RigdError, TakeError
from rigd.core.events import EventArray
from rigd.core.frames import Frame
from rigd.take.seal import fail_take
from rigd.take.writer import TakeWriter

log = logging.getLogger(__name__)


class CaptureSession:
    """One take, run in the background: start, watch, stop, collect the result.

    `duration_s=None` runs until `request_stop`. The session stops by itself, and still
    finalizes what it has, when the disk runs low (free space under
    `writer.disk_reserve_mb`) or the file system refuses a write; it reconnects a camera or
    event sensor that disappears (every `reconnect_interval_s`, by default the rig config's
    `service.reconnect_interval_s`; 0 writes it off at once).
    """

    def __init__(
        self,
        config: RigConfig,
        out_dir: Path,
        *,
        duration_s: float | None = None,
        path: Path | None = None,
        label: str | None = None,
        reconnect_interval_s: float | None = None,
        disk_usage: DiskUsage = shutil.disk_usage,
        open_trigger: Callable[[], Trigger] | None = None,
    ) -> None:
        if duration_s is not None:
            check_duration(duration_s)
        self.config = config
        self.rate = config.trigger.settings.rate_hz
        self.n_pulses = None if duration_s is None else max(1, round(duration_s * self.rate))
        self.out_dir = out_dir
        self.path = path or new_take_path(out_dir, config.name, label)
        self._reconnect_interval_s = (
            config.service.reconnect_interval_s if reconnect_interval_s is None else reconnect_interval_s
        )
        writer_cfg = config.writer
        margin = writer_cfg.window_margin_us
        self._window = TakeWindow(
            self.rate,
            round(1e6 / self.rate) if margin is None else margin,
            None if self.n_pulses is None else self.n_pulses - 1,
        )
        self._virtual = config.on_virtual_time()
        self._control = RunControl()
        self._faults = FaultBoard()
        self._ledger = LossLedger(self._faults, self._trigger_link)
        self._queue = WriterQueue(
            config.writer.queue_items,
            config.writer.queue_put_timeout_s,
            self._ledger,
            self._faults,
            max_bytes=config.writer.queue_mb << 20,
        )
        self._disk = DiskWatch(
            out_dir, config.writer.disk_reserve_mb, self._faults, self._control, disk_usage
        )
        self._flush_watch = FlushWatch(config.writer.flush_interval_s, self._faults)
        self._trigger_live = LiveStats("trigger")
        self._trigger: TriggerChannel | None = None
        self._pulses_of_take: int | None = None
        """Pulses of the take, once the box has stopped (what a follower host's take ends at)."""
        self._open_trigger = open_trigger
        self._before_pulses: Callable[[], None] | None = None
        """Opens the trigger instead of `config.trigger.spec` (a follower host's remote trigger)."""
        self._watchdog: TriggerWatchdog | None = None
        self._channels: dict[str, DeviceChannel] = {}
        self._take: TakeWriter | None = None
        self._writer: WriterLoop | None = None
        self._ballast: Ballast | None = None
        self._threads: list[threading.Thread] = []
        self._writer_thread: threading.Thread | None = None
        self._state: SessionState = "new"
        self._phases: list[Phase] = ["capturing"]
        self._entered_with: dict[str, int] = {}
        self._drain_peak = 0
        self._t_wall = 0.0
        self._t_start: float | None = None
        self._control_thread: threading.Thread | None = None
        self._result: CaptureResult | None = None
        self._error: BaseException | None = None
        self._done = threading.Event()
        self.stop_wait: StopWait | None = None
        """How the stop's wait for the devices ended (None until the take has stopped)."""

    # -- public API ----------------------------------------------------------------------
    @property
    def state(self) -> SessionState:
        return self._state

    def start(self, before_pulses: Callable[[], None] | None = None) -> Path:
        """Open the devices, create the take and start the trigger; errors raise here.

        `before_pulses` runs once everything here is open and recording, just before the
        trigger starts (a multi-host coordinator arms the other hosts there); what it raises
        fails the start, before any pulse."""
        self._before_pulses = before_pulses
        if self._state != "new":
            raise RigdError("a capture session can only be started once")
        self._state = "starting"
        self._t_wall = time.monotonic()
        check_out_dir(self.out_dir)
        made = [d for d in (self.out_dir, *self.out_dir.parents) if not d.exists()]
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            remove_stale_ballast(self.out_dir)
            self._disk.check(preflight=True)
            self._ballast = Ballast(self.out_dir, self.config.writer.disk_ballast_mb * 1_000_000)
            self._open()
        except BaseException as exc:
            self._abort(exc)
            self._state = "failed"
            self._error = exc
            self._done.set()
            self._remove_made_dirs(made)
            raise
        log.info(
            "capturing %s pulses at %.3f Hz into %s",
            self.n_pulses if self.n_pulses is not None else "until stopped:",
            self.rate,
            self.path,
        )
        self._state = "capturing"
        self._control_thread = threading.Thread(target=self._run, name="capture-control", daemon=True)
        self._control_thread.start()
        return self.path

    def _remove_made_dirs(self, made: list[Path]) -> None:
        """A take that did not start leaves no directory it made behind (when nothing is in it)."""
        for d in made:
            try:
                d.rmdir()
            except FileNotFoundError:
                continue
            except OSError as exc:  # not empty: something else wrote there meanwhile
                log.warning("leaving directory %s: %s", d, exc.strerror)
                return

    def request_stop(self, reason: str = "stop requested", *, hurry: bool = False) -> None:
        """Stop after the current pulse; the take is finalized as usual. `hurry` (a signal): the
        stop's waits end at `writer.stop_backlog_s` of wall-clock time, even on virtual time."""
        self._control.request_stop(reason, hurry=hurry)

    def wait(self, timeout: float | None = None) -> CaptureResult | None:
        """The result once done (None on timeout); re-raises what ended the take."""
        if not self._done.wait(timeout):
            return None
        if self._error is not None:
            raise self._error
        return self._result

    def pulse_feed(self, since: int) -> FeedState:
        """The pulse records from `since` on and where the box stands: what follower hosts of a
        multi-host rig fetch (`RemoteTrigger`)."""
        trigger = self._trigger
        if trigger is None:  # no trigger yet to read the take's host clock from: no clock reading
            over = self._state in ("failed", "done")
            empty = np.empty(0, np.int64)
            return FeedState(empty, empty, not over, 0 if over else None, 0, empty, None)
        now = trigger.device.host_clock.now_ns()  # the clock the records' host times are on
        index, t_us, host_ns = trigger.records_since(since)
        emitted = self._pulses_of_take
        if emitted is None and self._state in ("failed", "done"):
            emitted = trigger.n_pulses
        last = trigger.records_since(max(0, trigger.n_pulses - 1))[1]
        clock = int(last[-1]) if len(last) else 0
        return FeedState(index, t_us, emitted is None, emitted, clock, host_ns, now)

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
        counts = {name: ch.stream.written for name, ch in self._channels.items()}
        pulses = 0 if self._trigger is None else self._trigger.n_pulses
        depth = self._queue.qsize()
        phases = tuple(self._phases)
        phase = phases[-1]
        done: int | None = pulses
        total: int | None = self.n_pulses
        if phase == "waiting for devices":
            channels = list(self._channels.values())
            done, total = sum(ch.window_reached() for ch in channels), len(channels)
        elif phase == "draining":
            self._drain_peak = max(self._drain_peak, depth)
            done, total = self._drain_peak - depth, self._drain_peak
        elif phase == "finalizing":
            done = total = None
        return Progress(
            pulses,
            self.n_pulses or 0,
            {c.name: counts.get(c.name, 0) for c in self.config.cameras},
            {s.name: counts.get(s.name, 0) for s in self.config.event_sensors},
            depth,
            phase,
            done,
            total,
            phases,
            dict(self._entered_with),
        )

    def _enter(self, phase: Phase) -> None:
        """The take moves on to the next stop phase (see `results.StopPhase`)."""
        if phase == "draining":
            self._drain_peak = self._entered_with[phase] = self._queue.qsize()
        elif phase == "waiting for devices":
            self._entered_with[phase] = len(self._channels)
        self._phases.append(phase)
        log.debug("take %s: %s", self.path, phase)

    def snapshot(self) -> SessionSnapshot:
        now = time.monotonic()
        lost = self._ledger.lost_by_device()
        period_us = 1e6 / self.rate
        self._trigger_live.update_rate(now)
        devices = [self._trigger_live.snapshot("trigger", lost.get("trigger", 0), None)]
        for name, ch in list(self._channels.items()):
            ch.live.update_rate(now)
            shed = ch.shedding.shed_events
            jitter = ch.stream.obs.interval_jitter_us(period_us)
            devices.append(ch.live.snapshot(name, lost.get(name, 0), jitter, shed))
        try:
            size = self.path.stat().st_size
        except OSError:
            size = 0
        writer = self._writer
        last_flush = None if writer is None else writer.last_flush_mono
        return SessionSnapshot(
            self._state,
            self.path,
            0.0 if self._t_start is None else now - self._t_start,
            self.progress().pulses,
            self.n_pulses,
            self._queue.qsize(),
            self._queue.maxsize,
            size,
            devices,
            self._faults.active(),
            None if last_flush is None else now - last_flush,
            0.0 if self._take is None else self._take.flush_seconds_max,
            0.0 if writer is None else writer.load.fraction(),
            self._queue.bytes_queued,
            self._queue.max_bytes,
        )

    def latest_frames(self) -> dict[str, Frame]:
        frames = {name: ch.stream.latest_frame for name, ch in list(self._channels.items())}
        return {name: frame for name, frame in frames.items() if frame is not None}

    def latest_events(self) -> dict[str, tuple[EventArray, tuple[int, int]]]:
        views = {name: ch.event_view() for name, ch in list(self._channels.items())}
        return {name: view for name, view in views.items() if view is not None}

    # -- opening -------------------------------------------------------------------------
    def _trigger_link(self) -> dict[str, int]:
        return {} if self._trigger is None else self._trigger.device.link_stats()

    def _open(self) -> None:
        config = self.config
        trigger = self._trigger = TriggerChannel(
            config.trigger.spec,
            config.trigger.settings,
            self._control,
            self._faults,
            self._trigger_live,
            self._window,
            device=None if self._open_trigger is None else self._open_trigger(),
        )
        ctx = ChannelContext(
            self._control,
            self._queue,
            self._ledger,
            self._faults,
            trigger,
            1e6 / self.rate,
            self._reconnect_interval_s,
        )
        open_channels(config, ctx, self._channels)  # an abort closes those that opened
        self._agree_host_clock(trigger.device)
        prepare_rig(config, trigger, self._channels, self.n_pulses)
        for ch in self._channels.values():
            ch.open_gate(self._window, config.writer.window_hold_s)
        self._take = self._create_take(trigger)
        writer = self._writer = WriterLoop(
            self._take,
            self._queue,
            writer_streams([ch.stream for ch in self._channels.values()], self._trigger_live),
            self._ledger,
            self._faults,
            self._control,
            self._ballast,
            config.writer.flush_interval_s,
            relieve_at=config.writer.uncompressed_when_behind,
        )
        self._writer_thread = self._control.start_thread("writer", writer.run, daemon=False)
        self._threads = [
            self._control.start_thread(f"acq-{name}", ch.run) for name, ch in self._channels.items()
        ]
        self._threads.append(self._control.start_thread("acq-trigger", lambda: trigger.run(self._queue)))
        for ch in self._channels.values():
            ch.device.start()
        if self._before_pulses is not None:
            self._before_pulses()
        trigger.device.arm()
        self._t_start = time.monotonic()
        trigger.device.start(self.n_pulses)
        self._watchdog = TriggerWatchdog(trigger.device, self.rate, self._faults, probe_always=self._virtual)
        for live in [self._trigger_live, *(ch.live for ch in self._channels.values())]:
            live.samples.clear()

    def _agree_host_clock(self, trigger: Trigger) -> None:
        """The take's host clock is the trigger's (`ChannelContext.host_clock`); a follower
        host's remote trigger takes its devices' (a simulated world's on virtual time), as a
        box cabled here would stamp with it. A device on another clock is named: its host times
        cannot be compared with the pulse records'."""
        clocks = {id(c): c for c in (ch.device.host_clock for ch in self._channels.values())}
        if isinstance(trigger, RemoteTrigger) and len(clocks) == 1:
            trigger.use_host_clock(next(iter(clocks.values())))
        for name, ch in self._channels.items():
            if ch.device.host_clock is not trigger.host_clock:
                log.warning(
                    "%s stamps host time on %r, the trigger on %r: its host-time placement "
                    "(coarse sync, window by host time) compares two clocks",
                    name,
                    ch.device.host_clock,
                    trigger.host_clock,
                )

    def _create_take(self, trigger: TriggerChannel) -> TakeWriter:
        config = self.config
        take = TakeWriter(
            self.path,
            rig_config_json=config.model_dump_json(),
            take_id=self.path.stem,
            config=config.writer,
            rigd_version=__version__,
            flush_interval_s=config.writer.flush_interval_s,
        )
        try:
            take.add_trigger(trigger.device.info)
            for ch in self._channels.values():
                ch.add_to_take(take)
            store_ground_truth(take, {name: ch.device.info for name, ch in self._channels.items()})
        except BaseException:
            self._take = take  # marked failed and closed by the abort
            raise
        return take

    # -- watching ------------------------------------------------------------------------
    def _run(self) -> None:
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
            self._close_devices()
            self._done.set()

    def _watch(self) -> None:
        """Until the pulses are out, a stop is asked for or something fatal happens."""
        trigger, watchdog, control = self._trigger, self._watchdog, self._control
        assert trigger is not None
        assert watchdog is not None
        n_total = self.n_pulses
        # A rig on virtual time has no wall-clock pace to hold its pulses to.
        deadline = (
            None if n_total is None or self._virtual else time.monotonic() + n_total / self.rate * 1.5 + 5.0
        )
        next_disk = 0.0
        while True:
            if (error := control.first_error) is not None:
                raise error
            if control.stop_requested.is_set():
                log.info("stopping take %s: %s", self.path, control.stop_reason)
                return
            if n_total is not None and trigger.n_pulses >= n_total:
                return
            if (lost := trigger.device.link_lost()) is not None:
                log.error("stopping take %s: %s", self.path, lost)
                control.request_stop(f"the pulse records stopped coming: {lost}", fault=True)
                return
            now = time.monotonic()
            if (
                deadline is not None
                and n_total is not None
                and trigger.device.follows
                and not trigger.n_pulses
            ):
                # Another host starts the box once every host is armed: the pace counts from its first pulse.
                deadline = now + n_total / self.rate * 1.5 + 5.0
            watchdog.check()
            if now >= next_disk:
                self._disk.check()
                self._check_flushes(now)
                next_disk = now + 1.0
            if deadline is not None and now > deadline:
                msg = f"the trigger delivered {trigger.n_pulses} of {n_total} pulse records in time"
                log.error("take %s: %s; finalizing what there is", self.path, msg)
                control.request_stop(msg, fault=True)
                return
            time.sleep(0.05)

    def _check_flushes(self, now: float) -> None:
        writer = self._writer
        if writer is None or writer.error is not None or self._t_start is None:
            return
        self._flush_watch.check(
            now, self._t_start if writer.last_flush_mono is None else writer.last_flush_mono
        )

    # -- the end -------------------------------------------------------------------------
    def _finish(self) -> CaptureResult:
        trigger, writer, take = self._trigger, self._writer, self._take
        assert trigger is not None
        assert writer is not None
        assert take is not None
        assert self._writer_thread is not None
        assert self._t_start is not None
        t_stop = time.monotonic()
        self._control.enter_stop()
        stop = AcquisitionStop(
            self.path,
            self.config.writer.stop_backlog_s,
            self._virtual,
            self._window,
            trigger,
            self._channels,
            self._control,
            self._ledger,
            self._faults,
        )
        emitted = stop.stop_trigger()
        self._pulses_of_take = emitted
        self._enter("waiting for devices")
        behind = stop.wait_for_window()
        self._enter("draining")
        self.stop_wait = stop.stop_devices(t_stop, behind, self._threads)
        for ch in self._channels.values():
            ch.collect_counters()
        outside = stop.record_window(self.stop_wait)
        self._queue.put_stop()
        self._writer_thread.join()
        self._writer_thread = None
        capture_s = time.monotonic() - self._t_start
        self._enter("finalizing")
        if (error := self._control.first_error) is not None:
            raise error
        if writer.error is not None:
            if writer.last_flush_utc is None:  # nothing ever reached the disk for good
                written = self.path.stat().st_size if self.path.exists() else 0
                raise TakeError(
                    f"take {self.path} stopped, {self._control.stop_reason}; it stopped before its first "
                    f"flush, so it holds no recorded data ({written / 1e6:.1f} MB were written but never "
                    "made whole) and `rigd recover` cannot bring any back: free space, and delete it"
                )
            raise TakeError(
                f"take {self.path} stopped, {self._control.stop_reason}; everything up to the last flush "
                f"({writer.last_flush_utc}) is in the file; free space and run `rigd recover` to seal it"
            )
        window = (self._window.start_us, self._window.end_us, self._window.margin_us, outside)
        parts = (self._channels, self._ledger, self._faults, self._control)
        report, reason = finalize_take(self.config, take, trigger, *parts, emitted, window)
        counts = {name: ch.stream.written for name, ch in self._channels.items()}
        counts.update(take.events_in_take())  # EVT words: a packet across a window edge is clipped on read
        return CaptureResult(
            self.path,
            report,
            {c.name: counts[c.name] for c in self.config.cameras},
            {s.name: counts[s.name] for s in self.config.event_sensors},
            self.path.stat().st_size,
            time.monotonic() - self._t_wall,
            capture_s,
            flushes=take.flush_count,
            flush_max_s=take.flush_seconds_max,
            end_reason=reason,
            window_start_us=self._window.start_us,
            window_end_us=self._window.end_us,
            outside_window=take.window_outside() or outside,
        )

    def _abort(self, exc: BaseException) -> None:
        self._control.acquiring_done.set()
        if self._trigger is not None:
            try:
                self._trigger.device.stop()
            except RigdError as stop_exc:
                log.error("could not stop the trigger: %s", stop_exc)
        for th in self._threads:
            th.join(timeout=5)
        if self._writer_thread is not None:
            self._queue.put_stop()
            self._writer_thread.join(timeout=30)
        if self._take is not None:
            # Everything written so far stays in the file, marked failed with the reason
            # (after a full disk, in the room the released ballast made).
            try:
                fail_take(self._take, " ".join(f"{type(exc).__name__}: {exc}".split()))  # one line
            except (OSError, TakeError) as fail_exc:
                log.error("could not mark take %s failed: %s", self.path, fail_exc)
        if self._control_thread is None or threading.current_thread() is not self._control_thread:
            self._close_take()
            self._close_devices()

    def _close_take(self) -> None:
        try:
            if self._take is not None:
                try:
                    self._take.close()
                except OSError as exc:  # what was flushed stays on disk
                    log.error("closing take %s: %s", self.path, exc)
        finally:
            if self._ballast is not None:
                self._ballast.release()

    def _close_devices(self) -> None:
        """Close every device, together and within a bound (a device whose close does not return
        is left behind, logged: the take is already sealed or marked failed)."""
        closes = BoundedCalls("device close")
        for name, ch in self._channels.items():
            closes.start(name, ch.close)
        trigger = self._trigger
        if trigger is not None:

            def close_trigger() -> None:
                try:
                    trigger.device.close()
                except RigdError as exc:
                    log.error("closing %s failed: %s", trigger.device.info.spec, exc)

            closes.start("trigger", close_trigger)
        closes.join(time.monotonic() + self.config.writer.stop_backlog_s + CLOSE_BOUND_S)
