"""The capture pipeline: per-device acquisition threads, one bounded queue, one writer.

Acquisition threads only read from their device and enqueue; the writer thread owns the
take file. A full queue blocks an acquisition thread for `queue_put_timeout_s`, after
which the item is counted as lost with its time range, never dropped silently. After the
trigger box has emitted its pulses the devices are drained, the sync engine fits every
device clock, and the writer maps all timestamps to rig time.
"""

from __future__ import annotations

import functools
import json
import logging
import queue
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from drivers.base import EventPacket, EventSensor, PulseBatch, RgbCamera, Trigger
from drivers.registry import open_device
from rigd import __version__
from rigd.config import RigConfig
from rigd.core.errors import DeviceError, RigdError, TakeError
from rigd.core.frames import Frame
from rigd.core.schema import LossKind, LossRecord, SyncReport
from rigd.sync import DeviceObservations, PulseLog, synchronize
from rigd.take.writer import TakeWriter

log = logging.getLogger(__name__)

_READ_TIMEOUT_S = 0.05
_FLUSH_EVERY_S = 1.0
_STOP = object()


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


class _Pipeline:
    def __init__(self, config: RigConfig, path: Path) -> None:
        self.config = config
        self.path = path
        self.queue: queue.Queue[Any] = queue.Queue(maxsize=config.writer.queue_items)
        self.stop_acq = threading.Event()
        self.errors: list[BaseException] = []
        self.losses: list[LossRecord] = []
        self.lock = threading.Lock()
        self.obs: dict[str, _Observations] = {}
        self.frames: dict[str, int] = {c.name: 0 for c in config.cameras}
        self.events: dict[str, int] = {s.name: 0 for s in config.event_sensors}
        self.device_counters: dict[str, dict[str, int]] = {}
        self.failed_devices: dict[str, str] = {}
        self.trigger_channel = {s.name: s.settings.trigger_in_channel for s in config.event_sensors}
        self.pulses: list[PulseBatch] = []
        self.trigger: Trigger | None = None
        self.cameras: dict[str, RgbCamera] = {}
        self.sensors: dict[str, EventSensor] = {}
        self.threads: list[threading.Thread] = []
        self.writer: TakeWriter | None = None

    # -- devices -------------------------------------------------------------------------
    def open_devices(self) -> None:
        cfg = self.config
        self.trigger = open_device("trigger", cfg.trigger.spec)
        self.trigger.configure(cfg.trigger.settings)
        for cam in cfg.cameras:
            dev = open_device("rgb_camera", cam.spec)
            self.cameras[cam.name] = dev
            dev.configure(cam.settings)
        for sen in cfg.event_sensors:
            ev = open_device("event_sensor", sen.spec)
            self.sensors[sen.name] = ev
            ev.configure(sen.settings)
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

    # -- acquisition threads -------------------------------------------------------------
    def _put(
        self, device: str, what: LossKind, item: Any, t_range: tuple[int, int] | None, count: int
    ) -> None:
        try:
            self.queue.put(item, timeout=self.config.writer.queue_put_timeout_s)
        except queue.Full:
            log.warning("writer queue full: %d %s of %s lost", count, what, device)
            with self.lock:
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

    def _guard(self, name: str, fn: Callable[[], None], device: str | None = None) -> Callable[[], None]:
        """Run a thread body; an error ends the capture, except a camera or event sensor that
        fails (unplugged, say): that device is written off with a loss record and the take
        goes on with the others."""

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
                with self.lock:
                    self.failed_devices[device] = str(exc)
                    self.losses.append(
                        LossRecord(
                            device=device,
                            what="frames" if device in self.cameras else "events",
                            count=0,
                            reason=f"device failed mid-take; no data after this point: {exc}",
                        )
                    )
            except BaseException as exc:  # recorded and re-raised by the main thread
                log.exception("acquisition thread %s failed", name)
                with self.lock:
                    self.errors.append(exc)
                self.stop_acq.set()

        return run

    def _camera_loop(self, name: str, cam: RgbCamera) -> None:
        while True:
            frame = cam.read_frame(_READ_TIMEOUT_S)
            if frame is None:
                if self.stop_acq.is_set():
                    return
                continue
            t = frame.t_exposure_start_us
            self._put(name, "frames", ("frame", name, frame), (t, t), 1)

    def _sensor_loop(self, name: str, sensor: EventSensor) -> None:
        while True:
            packet = sensor.read_events(_READ_TIMEOUT_S)
            if packet is None:
                if self.stop_acq.is_set():
                    return
                continue
            ev = packet.events
            t_range = (int(ev.t[0]), int(ev.t[-1])) if len(ev) else None
            self._put(name, "events", ("events", name, packet), t_range, len(ev))

    def _trigger_loop(self, trigger: Trigger) -> None:
        while True:
            batch = trigger.read_pulses(_READ_TIMEOUT_S)
            if len(batch):
                with self.lock:
                    self.pulses.append(batch)
                self._put("trigger", "pulses", ("pulses", "trigger", batch), None, len(batch))
            elif self.stop_acq.is_set():
                return

    def start_threads(self) -> None:
        assert self.trigger is not None
        targets: list[tuple[str, Callable[[], None], str | None]] = [
            (f"acq-{n}", functools.partial(self._camera_loop, n, c), n) for n, c in self.cameras.items()
        ]
        targets += [
            (f"acq-{n}", functools.partial(self._sensor_loop, n, s), n) for n, s in self.sensors.items()
        ]
        targets.append(("acq-trigger", functools.partial(self._trigger_loop, self.trigger), None))
        for name, fn, device in targets:
            th = threading.Thread(target=self._guard(name, fn, device), name=name, daemon=True)
            th.start()
            self.threads.append(th)

    # -- writer thread -------------------------------------------------------------------
    def writer_loop(self) -> None:
        writer = self.writer
        assert writer is not None
        last_flush = time.monotonic()
        while True:
            try:
                item = self.queue.get(timeout=0.2)
            except queue.Empty:
                item = None
            if item is _STOP:
                writer.flush()
                return
            if item is not None:
                kind, name, payload = item
                try:
                    self._write(writer, kind, name, payload)
                except TakeError as exc:
                    # Bad data from one device must not cost the rest of the take.
                    log.error("refused data from %s: %s", name, exc)
                    with self.lock:
                        self.losses.append(
                            LossRecord(device=name, what=_what(kind), count=_count(payload), reason=str(exc))
                        )
            now = time.monotonic()
            if now - last_flush >= _FLUSH_EVERY_S:
                writer.flush()
                last_flush = now

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
        elif kind == "events":
            packet: EventPacket = payload
            if len(packet.events):
                writer.append_events(name, packet.events)
            if len(packet.triggers):
                writer.append_triggers(name, packet.triggers)
                rising = packet.triggers.rising(self.trigger_channel[name])
                obs = self.obs[name]
                obs.t.extend(rising.t.tolist())
                obs.host.extend([packet.host_time_ns] * len(rising))
            self.events[name] += len(packet.events)
        elif kind == "pulses":
            writer.append_pulses(payload)

    def progress(self, n_total: int) -> Progress:
        with self.lock:
            n = sum(len(b) for b in self.pulses)
        return Progress(n, n_total, dict(self.frames), dict(self.events), self.queue.qsize())


def _what(kind: str) -> LossKind:
    kinds: dict[str, LossKind] = {"frame": "frames", "events": "events", "pulses": "pulses"}
    return kinds[kind]


def _count(payload: Any) -> int:
    if isinstance(payload, Frame):
        return 1
    if isinstance(payload, EventPacket):
        return len(payload.events)
    return len(payload)


def new_take_path(out_dir: Path, rig_name: str) -> Path:
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    return out_dir / f"{rig_name}-{stamp}-{uuid.uuid4().hex[:6]}.h5"


def run_capture(
    config: RigConfig,
    out_dir: Path,
    duration_s: float,
    *,
    on_progress: Callable[[Progress], None] | None = None,
    path: Path | None = None,
) -> CaptureResult:
    """Capture one take of `duration_s` seconds of trigger pulses and return its summary."""
    if duration_s <= 0:
        raise RigdError(f"duration must be positive, got {duration_s}")
    rate = config.trigger.settings.rate_hz
    n_pulses = max(1, round(duration_s * rate))
    out_dir.mkdir(parents=True, exist_ok=True)
    path = path or new_take_path(out_dir, config.name)
    pipe = _Pipeline(config, path)
    t_wall = time.monotonic()
    writer_thread: threading.Thread | None = None
    try:
        pipe.open_devices()
        assert pipe.trigger is not None
        writer = TakeWriter(
            path,
            rig_config_json=config.model_dump_json(),
            take_id=path.stem,
            config=config.writer,
            rigd_version=__version__,
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
        writer_thread = threading.Thread(target=pipe._guard("writer", pipe.writer_loop), name="writer")
        writer_thread.start()
        pipe.start_threads()
        for cam in pipe.cameras.values():
            cam.start()
        for sen in pipe.sensors.values():
            sen.start()
        pipe.trigger.arm()
        t_start = time.monotonic()
        pipe.trigger.start(n_pulses)
        log.info("capturing %d pulses at %.3f Hz into %s", n_pulses, rate, path)
        _wait_for_pulses(pipe, n_pulses, rate, on_progress)
        emitted = pipe.trigger.stop()
        # Let the last exposures and event slices reach the host before stopping devices.
        _drain_wait(pipe, rate)
        devices: dict[str, RgbCamera | EventSensor] = {**pipe.sensors, **pipe.cameras}
        for name, dev in devices.items():
            _stop_device(pipe, name, dev)
        pipe.stop_acq.set()
        for th in pipe.threads:
            th.join()
        _record_device_losses(pipe)
        pipe.queue.put(_STOP)
        writer_thread.join()
        writer_thread = None
        capture_s = time.monotonic() - t_start
        if pipe.errors:
            raise pipe.errors[0]
        result = _finalize(pipe, emitted, rate)
        if on_progress:
            on_progress(pipe.progress(n_pulses))
        return CaptureResult(
            path,
            result,
            dict(pipe.frames),
            dict(pipe.events),
            path.stat().st_size,
            time.monotonic() - t_wall,
            capture_s,
        )
    except BaseException as exc:
        pipe.stop_acq.set()
        if pipe.trigger is not None:
            try:
                pipe.trigger.stop()
            except RigdError as stop_exc:
                log.error("could not stop the trigger: %s", stop_exc)
        for th in pipe.threads:
            th.join(timeout=5)
        if writer_thread is not None:
            pipe.queue.put(_STOP)
            writer_thread.join(timeout=30)
        if pipe.writer is not None:
            # Everything written so far stays in the file, marked failed with the reason.
            pipe.writer.fail(f"{type(exc).__name__}: {exc}")
        raise
    finally:
        if pipe.writer is not None:
            pipe.writer.close()
        pipe.close_devices()


def _stop_device(pipe: _Pipeline, name: str, dev: RgbCamera | EventSensor) -> None:
    try:
        dev.stop()
    except DeviceError as exc:
        if name not in pipe.failed_devices:
            raise
        log.warning("stopping failed device %s: %s", name, exc)


def _wait_for_pulses(
    pipe: _Pipeline, n_pulses: int, rate: float, on_progress: Callable[[Progress], None] | None
) -> None:
    assert pipe.trigger is not None
    deadline = time.monotonic() + n_pulses / rate * 1.5 + 5.0
    while True:
        if pipe.errors:
            raise pipe.errors[0]
        prog = pipe.progress(n_pulses)
        if on_progress:
            on_progress(prog)
        if prog.pulses >= n_pulses:
            return
        if time.monotonic() > deadline:
            if not pipe.trigger.is_running():
                log.warning("trigger stopped after %d of %d pulse records", prog.pulses, n_pulses)
                return
            raise DeviceError(
                f"trigger {pipe.config.trigger.spec!r} reported {prog.pulses} of {n_pulses} pulses in time"
            )
        time.sleep(0.05)


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
        if stats.extra.get("triggers_late"):
            pipe.losses.append(
                LossRecord(
                    device=name,
                    what="triggers",
                    count=stats.extra["triggers_late"],
                    reason="trigger edges arrived after their part of the stream was sent",
                )
            )


def _finalize(pipe: _Pipeline, emitted: int, rate: float) -> SyncReport:
    assert pipe.writer is not None
    batches = pipe.pulses
    index = np.concatenate([b.index for b in batches]) if batches else np.empty(0, np.int64)
    order = np.argsort(index, kind="stable")
    uniq = np.concatenate([[True], np.diff(index[order]) > 0]) if index.size else np.empty(0, bool)
    sel = order[uniq]
    pulses = PulseLog(
        index[sel],
        (np.concatenate([b.t_us for b in batches]) if batches else np.empty(0, np.int64))[sel],
        (np.concatenate([b.host_time_ns for b in batches]) if batches else np.empty(0, np.int64))[sel],
        max(emitted, int(index.max(initial=-1)) + 1),
    )
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
    if pipe.trigger is not None:
        result.report.trigger_link = pipe.trigger.link_stats()
    frame_index = {name: result.observation_pulse_index[name] for name in pipe.cameras}
    pipe.writer.finalize(result.maps, frame_index, result.report)
    log.info("take %s finalized: %s", pipe.path, json.dumps(pipe.frames))
    return result.report
