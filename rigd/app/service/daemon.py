"""`rigd serve`: the capture daemon.

One thread serves the control socket (ROUTER, so REQ clients see plain request/reply), one
publishes telemetry (PUB) and feeds the Prometheus exporter and the systemd watchdog, and at
most one `CaptureSession` runs in the background. Opening the devices for a take can take
seconds on real hardware, enumerating cameras too, and sealing big takes minutes, so those
run on worker threads whose replies are sent when they are done: meanwhile the control loop
keeps answering (`status` says `starting`, `stop` is queued) and feeding the systemd watchdog.
What each command does is `rigd.app.service.handlers`'; who has the rig (the take, a recovery,
a holder) and what the last take left is `rigd.app.service.rig_slot`'s. This module serves.

Every request gets a reply: malformed input is answered with a structured error, and a bug
in a handler is logged and answered as `internal` while the daemon goes on serving.
SIGTERM/SIGINT finalize the running take before exiting. Should the control loop die anyway
(an exception escaping it), the running take is finalized and `serve` raises
`ControlPlaneError`: a daemon nobody can talk to must not go on recording (`rigd serve`
exits non-zero, and systemd restarts it).
"""

from __future__ import annotations

import functools
import logging
import os
import shutil
import signal
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path
from types import FrameType
from typing import Any, Protocol

import zmq

from rigd import __version__
from rigd.app.capture import CaptureSession, SessionSnapshot, remove_stale_ballast
from rigd.app.config import RigConfig
from rigd.app.service import sdnotify
from rigd.app.service.client import find_daemon
from rigd.app.service.endpoints import DaemonRunningError, apply_server_curve, bind, start_authenticator
from rigd.app.service.handlers import Handlers
from rigd.app.service.metrics import MetricsExporter
from rigd.app.service.protocol import (
    PAYLOAD_KEY,
    DeviceTelemetry,
    Reply,
    Telemetry,
    ThumbnailHeader,
)
from rigd.app.service.requests import (
    RequestError,
    decode_request,
    error_info,
    reply_bytes,
    split_envelope,
    validate_request,
)
from rigd.app.service.rig_slot import RigSlot, by_kind, fault
from rigd.app.service.thumbnails import events_thumbnail, frame_thumbnail
from rigd.app.service.workers import WorkerPool
from rigd.core.errors import ConfigError, RigdError
from rigd.core.kinds import DeviceKind

log = logging.getLogger(__name__)

#: Below this writer load the capacity estimate (rate / load) is too noisy to show.
MIN_BUSY_FOR_CAPACITY = 0.05

#: Messages up to this size are read and refused with `too_large`; ZeroMQ drops bigger
#: ones at the transport (the peer is disconnected) so they never reach memory.
_HARD_LIMIT_BYTES = 1 << 20

#: How long shutdown waits for a capture that is still opening its devices.
_WORKER_GRACE_S = 60.0

#: Commands that can take seconds to minutes (opening devices, enumerating cameras, sealing
#: big takes): run on a worker so the control loop answers and feeds the watchdog meanwhile.
_SLOW_COMMANDS = frozenset({"capture", "capture_part", "devices", "recover"})

#: Of those, the ones that act on the rig: their claim (`_claim`) lets one run at a time, so
#: each gets its own thread and is never refused for a queue full of other requests.
_RIG_COMMANDS = frozenset({"capture", "capture_part", "recover"})

#: Worker threads for the other slow commands (`devices`), and how many requests may wait
#: for one; beyond that a request is answered `busy` at once. Without a bound, a client
#: flooding `devices` made a thread per request and starved the control loop (2,000
#: requests: 79 threads, `ping` 1.5-3.9 s).
POOL_WORKERS = 3
POOL_QUEUE = 8
_POOL_THREAD = "control-worker"

#: Takes a command and a job that returns reply bytes and sees that the reply gets sent
#: (raises `RequestError` busy when it cannot take the job now).
_Defer = Callable[[str, Callable[[], list[bytes]]], None]

#: Where workers hand finished replies back to the control loop, which owns the socket.
_REPLIES_ENDPOINT = "inproc://rigd-deferred-replies"


class ControlPlaneError(RigdError):
    """The control loop died (a bug); the running take was finalized and the daemon exits."""


class Attachment(Protocol):
    """Something served alongside the daemon (the web console, the start-up announcement):
    started in order once the sockets are bound, before `ready`; closed in reverse at exit."""

    def start(self, daemon: Daemon) -> None: ...

    def close(self) -> None: ...


def _utc() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


class Daemon:
    """The daemon's state; `serve()` runs until `shutdown()` or a signal."""

    def __init__(
        self, config: RigConfig, *, metrics: bool = True, attachments: Sequence[Attachment] = ()
    ) -> None:
        self.config = config
        self._attachments = list(attachments)
        self.svc = config.service
        self.rig = RigSlot(config)
        """Who has the rig (a take, a recovery, a holder) and what the last take left."""
        self._seq = 0
        self._stop = threading.Event()
        self._handlers = Handlers(config, self.rig, telemetry=self.telemetry, stop=self._stop)
        self._ready = threading.Event()
        self._ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
        self._auth: Any = None
        self._metrics = (
            MetricsExporter(self.svc.metrics_host, self.svc.metrics_port, self.svc.metrics_token_file)
            if (metrics and self.svc.metrics_port is not None)
            else None
        )
        self._loop_beat = time.monotonic()
        self._workers: list[threading.Thread] = []
        self._pool = WorkerPool(POOL_WORKERS, POOL_QUEUE, _POOL_THREAD)
        self._refused = 0  # requests refused busy since the pool last took one
        self._disk_error: str | None = None

    # -- lifecycle -----------------------------------------------------------------------
    def serve(self) -> None:
        """Recover, bind, notify systemd, serve; blocks until shut down."""
        control = self.svc.control_endpoint
        existing = find_daemon(control, timeout_s=1.0)
        if existing is not None:
            existing.close()
            raise DaemonRunningError(f"a rigd daemon already answers at {control}")
        try:
            self.svc.take_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(f"service.take_dir: cannot create {self.svc.take_dir}: {exc.strerror}") from exc
        if n := remove_stale_ballast(self.svc.take_dir):
            log.warning("removed %d disk ballast file(s) a killed daemon left in %s", n, self.svc.take_dir)
        if self.svc.recover_on_start:
            self.rig.recover()
        rep = self._ctx.socket(zmq.ROUTER)
        pub = self._ctx.socket(zmq.PUB)
        for sock in (rep, pub):
            sock.setsockopt(zmq.LINGER, 0)
            sock.setsockopt(zmq.MAXMSGSIZE, _HARD_LIMIT_BYTES)
        pub.setsockopt(zmq.SNDHWM, 100)  # a slow subscriber loses telemetry, never stalls us
        if self.svc.curve is not None:
            self._auth = start_authenticator(self._ctx, self.svc.curve)
            for sock in (rep, pub):
                apply_server_curve(sock, self.svc.curve)
        started: list[Attachment] = []
        telemetry: threading.Thread | None = None
        try:
            bind(rep, control, "control")
            bind(pub, self.svc.telemetry_endpoint, "telemetry")
            if self._metrics is not None:
                self._metrics.start()
            telemetry = threading.Thread(
                target=self._telemetry_loop, args=(pub,), name="telemetry", daemon=True
            )
            telemetry.start()
            for att in self._attachments:
                att.start(self)
                started.append(att)
            self._ready.set()
            sdnotify.notify("READY=1", f"STATUS=serving on {control}", f"MAINPID={os.getpid()}")
            log.info(
                "rigd %s serving on %s (telemetry %s)", __version__, control, self.svc.telemetry_endpoint
            )
            try:
                self._serve_loop(rep)
            except Exception as exc:
                # Nobody can stop a take through a dead control socket: finalize it now, then
                # exit non-zero (the cause is logged with its traceback).
                log.critical("control loop failed; finalizing the running take and exiting", exc_info=exc)
                sdnotify.notify("STOPPING=1", "STATUS=control loop failed; finalizing the take")
                self.rig.finish(f"control loop failed: {type(exc).__name__}")
                raise ControlPlaneError(f"the control loop failed ({type(exc).__name__}: {exc})") from exc
            sdnotify.notify("STOPPING=1", "STATUS=stopping")
            self.rig.finish("daemon shutting down")
        finally:
            # Also when a bind or an attachment failed: the telemetry thread must not outlive its
            # socket (it would log a failed tick every second for the rest of the process).
            self._stop.set()
            if telemetry is not None:
                telemetry.join(timeout=5)
            for att in reversed(started):
                att.close()
            rep.close(linger=0)
            pub.close(linger=0)
            if self._metrics is not None:
                self._metrics.close()
            if self._auth is not None:
                self._auth.stop()
            self._ctx.term()
            for ep in (control, self.svc.telemetry_endpoint):
                if ep.startswith("ipc://"):
                    Path(ep.removeprefix("ipc://")).unlink(missing_ok=True)
            log.info("rigd daemon stopped")

    @property
    def metrics_url(self) -> str | None:
        return None if self._metrics is None else self._metrics.url

    @property
    def recovered(self) -> list[dict[str, Any]]:
        """What recovery sealed or could not read (at start and on `recover`), oldest first."""
        return self.rig.recovered

    def current_session(self) -> CaptureSession | None:
        """The running take's session (for live previews), or None."""
        return self.rig.current_session()

    def hold_devices(self, holder: str) -> None:
        """Keep takes from starting while something else (a guided calibration) uses the devices;
        `busy` when a take runs or another holder has them. `release_devices` gives them back."""
        self.rig.hold_devices(holder)

    def release_devices(self) -> None:
        self.rig.release_devices()

    def wait_ready(self, timeout: float | None = None) -> bool:
        return self._ready.wait(timeout)

    def shutdown(self) -> None:
        self._stop.set()

    def install_signal_handlers(self) -> None:
        def handler(signum: int, frame: FrameType | None) -> None:
            log.warning("signal %s: finalizing and shutting down", signal.Signals(signum).name)
            self._stop.set()

        signal.signal(signal.SIGTERM, handler)
        signal.signal(signal.SIGINT, handler)

    # -- control socket ------------------------------------------------------------------
    def _serve_loop(self, sock: zmq.Socket[bytes]) -> None:
        replies = self._ctx.socket(zmq.PULL)
        replies.setsockopt(zmq.LINGER, 0)
        replies.bind(_REPLIES_ENDPOINT)
        poller = zmq.Poller()
        poller.register(sock, zmq.POLLIN)
        poller.register(replies, zmq.POLLIN)
        self._pool.start()
        pool_closed = False
        try:
            while not self._stop.is_set():
                self._loop_beat = time.monotonic()
                ready = dict(poller.poll(100))
                if replies in ready:
                    self._forward_replies(replies, sock)
                if sock in ready:
                    envelope, body = split_envelope(sock.recv_multipart(copy=True))
                    reply = self.handle_frames(body, defer=functools.partial(self._defer, envelope))
                    if reply is not None:
                        sock.send_multipart([*envelope, *reply])
            # A capture still opening its devices answers its client before the socket goes.
            for worker in self._workers:
                worker.join(timeout=_WORKER_GRACE_S)
            pool_closed = True
            self._pool.close(_WORKER_GRACE_S)
            self._forward_replies(replies, sock)
        finally:
            if not pool_closed:  # the loop failed: its workers must not outlive it
                self._pool.close(_WORKER_GRACE_S)
            replies.close(linger=0)

    @staticmethod
    def _forward_replies(replies: zmq.Socket[bytes], sock: zmq.Socket[bytes]) -> None:
        while True:
            try:
                sock.send_multipart(replies.recv_multipart(zmq.NOBLOCK))
            except zmq.Again:
                return

    def _defer(self, envelope: list[bytes], cmd: str, job: Callable[[], list[bytes]]) -> None:
        """Run `job` on a worker; its reply goes back to the client through the control loop.

        capture/recover get a thread each (their claim lets one run at a time); the rest go to
        the bounded pool, and a request it cannot take is refused `busy` here, at once."""

        def work() -> None:
            reply = job()
            try:
                push = self._ctx.socket(zmq.PUSH)
            except zmq.ZMQError as exc:  # the daemon is gone; the client times out
                log.warning("deferred reply not sent: %s", exc)
                return
            try:
                push.setsockopt(zmq.LINGER, 1000)
                push.connect(_REPLIES_ENDPOINT)
                push.send_multipart([*envelope, *reply], zmq.NOBLOCK)
            except zmq.ZMQError as exc:
                log.warning("deferred reply not sent: %s", exc)
            finally:
                push.close()

        if cmd not in _RIG_COMMANDS:
            if self._pool.submit(work):
                if self._refused:
                    log.warning("control workers take requests again (%d refused busy)", self._refused)
                    self._refused = 0
                return
            if not self._refused:  # once per flood, not once per request
                log.warning(
                    "%s refused busy: %d workers busy, %d requests waiting", cmd, POOL_WORKERS, POOL_QUEUE
                )
            self._refused += 1
            raise RequestError(
                "busy",
                f"{POOL_WORKERS} workers are busy and {POOL_QUEUE} requests wait for them; try again",
            )
        self._workers = [w for w in self._workers if w.is_alive()]
        worker = threading.Thread(target=work, name=f"control-{cmd}", daemon=True)
        self._workers.append(worker)
        worker.start()

    def handle(self, frames: list[bytes], defer: _Defer | None = None) -> bytes | None:
        """The JSON frame of `handle_frames`' reply (what every reply but a binary take_read is)."""
        reply = self.handle_frames(frames, defer)
        return None if reply is None else reply[0]

    def handle_frames(self, frames: list[bytes], defer: _Defer | None = None) -> list[bytes] | None:
        """Answer one request message (all its frames) with the reply's frames: the JSON, then
        a binary payload when the command has one; never raises.

        With `defer`, a slow command (capture, devices, recover) hands its work to `defer` and
        returns None: the reply comes from that job. Without it, everything is answered here.
        """
        try:
            return self._handle(frames, defer)
        except Exception as exc:  # noqa: BLE001 - a bug here must not end the control loop
            return [reply_bytes(Reply(ok=False, error=error_info(exc)))]

    def _handle(self, frames: list[bytes], defer: _Defer | None) -> list[bytes] | None:
        req_id: str | None = None
        try:
            data = decode_request(frames)
            rid = data.get("id")
            req_id = rid if isinstance(rid, str) and len(rid) <= 64 else None
            cmd, args = validate_request(data)
            if defer is not None and cmd in _SLOW_COMMANDS:
                job = self._handlers.claim(cmd, args)  # quick checks here; `busy` is answered at once
                deferred_id = req_id
                defer(cmd, lambda: self._answer(deferred_id, job))  # capture/recover: never busy here
                return None
        except Exception as exc:  # noqa: BLE001 - every failure is answered, the loop goes on
            return [reply_bytes(Reply(id=req_id, ok=False, error=error_info(exc)))]
        return self._answer(req_id, functools.partial(self._handlers.run, cmd, args))

    @staticmethod
    def _answer(req_id: str | None, fn: Callable[[], dict[str, Any]]) -> list[bytes]:
        """Run a command and turn its result or its error into the reply's frames: the JSON, and
        the result's PAYLOAD_KEY bytes as a second frame when it has them."""
        payload: bytes | None = None
        try:
            result = fn()
            payload = result.pop(PAYLOAD_KEY, None)
            out = Reply(id=req_id, ok=True, result=result)
        except Exception as exc:  # noqa: BLE001 - every failure is answered, the loop goes on
            out = Reply(id=req_id, ok=False, error=error_info(exc))
        frames = [reply_bytes(out)]
        return frames if payload is None or not out.ok else [*frames, payload]

    # -- telemetry -------------------------------------------------------------------------
    def telemetry(self) -> Telemetry:
        rig = self.rig
        rig.reap()
        with rig.lock:
            session = rig.session
            self._seq += 1
            seq = self._seq
            state = rig.state
            last, completed, idle_faults = rig.last_take, rig.takes_completed, list(rig.idle_faults)
        try:
            usage = shutil.disk_usage(self.svc.take_dir)
            free, total = usage.free, usage.total
            self._disk_error = None
        except OSError as exc:
            free = total = 0  # telemetry says 0 of 0 bytes; the log says why, once per cause
            if str(exc) != self._disk_error:
                self._disk_error = str(exc)
                log.warning("disk usage of %s unavailable: %s", self.svc.take_dir, exc)
        t = Telemetry(
            seq=seq,
            time_utc=_utc(),
            pid=os.getpid(),
            state=state,
            disk_free_bytes=free,
            disk_total_bytes=total,
            takes_completed=completed,
            last_take=last,
            faults=idle_faults,
            host=rig.host,
            hosts=rig.hosts(),
        )
        if session is None or session.state in ("new", "starting"):
            # While the devices open, their live counters are still being set up.
            t.devices = self._idle_devices()
            return t
        t = self._with_session(t, session.snapshot())
        t.take = str(session.path)  # a multi-host take: the joined take, not this host's part
        return t

    def _idle_devices(self) -> list[DeviceTelemetry]:
        kinds: list[tuple[str, DeviceKind]] = [("trigger", "trigger")]
        kinds += [(c.name, "rgb_camera") for c in self.config.cameras if c.host == self.rig.host]
        kinds += [(s.name, "event_sensor") for s in self.config.event_sensors if s.host == self.rig.host]
        return [
            DeviceTelemetry(name=name, kind=kind, state="idle", total=0, rate_hz=0.0, lost=0)
            for name, kind in kinds
        ]

    def _with_session(self, t: Telemetry, snap: SessionSnapshot) -> Telemetry:
        t.take = str(snap.path)
        t.take_elapsed_s = snap.elapsed_s
        t.pulses = snap.pulses
        t.queue_depth = snap.queue_depth
        t.queue_capacity = snap.queue_capacity
        t.queue_bytes = snap.queue_bytes
        t.queue_max_bytes = snap.queue_max_bytes
        t.writer_busy = snap.writer_busy
        events_hz = sum(by_kind(snap.devices, lambda d: d.rate_hz).get("event_sensor", {}).values())
        t.event_capacity_hz = (
            events_hz / snap.writer_busy if snap.writer_busy >= MIN_BUSY_FOR_CAPACITY else None
        )
        t.bytes_written = snap.bytes_written
        t.last_flush_age_s = snap.last_flush_age_s
        t.flush_max_s = snap.flush_max_s
        t.devices = [DeviceTelemetry.model_validate(asdict(d)) for d in snap.devices]
        t.faults = [fault(f) for f in snap.faults]
        return t

    def _telemetry_loop(self, pub: zmq.Socket[bytes]) -> None:
        interval = self.svc.telemetry_interval_s
        watchdog = sdnotify.watchdog_interval_s()
        tick = interval if watchdog is None else min(interval, watchdog)
        next_thumb = next_status = 0.0
        last_bytes, last_t = 0, time.monotonic()
        while not self._stop.wait(tick):
            now = time.monotonic()
            if watchdog is not None and self._control_alive(now, watchdog):
                # Pinged only while the control loop turns: a hung daemon gets restarted.
                sdnotify.notify("WATCHDOG=1", f"STATUS={self.rig.state}")
            if now < next_status:
                continue
            next_status = now + interval
            try:
                t = self.telemetry()
                t.write_rate_bytes_s = max(0.0, (t.bytes_written - last_bytes) / max(now - last_t, 1e-6))
                last_bytes, last_t = t.bytes_written, now
                pub.send_multipart([b"status", t.model_dump_json().encode()])
                if self._metrics is not None:
                    self._metrics.update(t)
                if self.svc.thumbnail_interval_s > 0 and now >= next_thumb:
                    self._publish_thumbnails(pub)
                    next_thumb = now + self.svc.thumbnail_interval_s
            except zmq.ZMQError as exc:
                if exc.errno in (zmq.ENOTSOCK, zmq.ETERM):  # the socket is gone: nothing to publish on
                    log.error("telemetry socket closed (%s); telemetry stops", exc)
                    return
                log.exception("telemetry tick failed")
            except Exception:
                # Telemetry must not take the daemon down; the next tick tries again.
                log.exception("telemetry tick failed")

    def _control_alive(self, now: float, watchdog_s: float) -> bool:
        return now - self._loop_beat < 2 * watchdog_s

    def _publish_thumbnails(self, pub: zmq.Socket[bytes]) -> None:
        session = self.rig.current_session()
        if session is None:
            return
        width = self.svc.thumbnail_width
        for name, frame in session.latest_frames().items():
            jpeg, w, h = frame_thumbnail(frame, width)
            head = ThumbnailHeader(device=name, kind="rgb_camera", width=w, height=h, time_utc=_utc())
            pub.send_multipart([f"thumb.{name}".encode(), head.model_dump_json().encode(), jpeg])
        for name, (events, geometry) in session.latest_events().items():
            jpeg, w, h = events_thumbnail(events, geometry, width)
            head = ThumbnailHeader(device=name, kind="event_sensor", width=w, height=h, time_utc=_utc())
            pub.send_multipart([f"thumb.{name}".encode(), head.model_dump_json().encode(), jpeg])


def run_daemon(config: RigConfig, attachments: Sequence[Attachment] = ()) -> None:
    """Entry point of `rigd serve`."""
    daemon = Daemon(config, attachments=attachments)
    daemon.install_signal_handlers()
    try:
        daemon.serve()
    except ControlPlaneError:
        sdnotify.notify("STATUS=control loop failed; take finalized")
        raise
    except RigdError:
        sdnotify.notify("STATUS=failed to start")
        raise
