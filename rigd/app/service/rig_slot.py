"""Who has the rig: the daemon's one take, a recovery of unfinished takes, or a holder.

At most one of them runs at a time; a request for another is answered `busy`. The slot also
keeps what the telemetry reports between takes: the last take's summary, how many takes were
completed, the faults that outlive a take (a full disk), and what recovery sealed.
"""

from __future__ import annotations

import ctypes
import functools
import gc
import logging
import threading
from collections.abc import Callable, Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any, Protocol, TypeVar

from rigd.app.capture import CaptureSession, SessionSnapshot
from rigd.app.capture.remote_trigger import FeedState
from rigd.app.config import RigConfig
from rigd.app.service import sdnotify
from rigd.app.service.host_links import this_host
from rigd.app.service.multihost import MultiHostSession as MultiHostRun
from rigd.app.service.protocol import (
    CaptureArgs,
    CapturePartArgs,
    DaemonState,
    Fault,
    HostTelemetry,
    PulsesArgs,
    TakeSummary,
)
from rigd.app.service.requests import RequestError
from rigd.core.errors import TakeError
from rigd.core.kinds import DeviceKind
from rigd.take.verdict import take_verdict

log = logging.getLogger(__name__)


class _Device(Protocol):
    name: str
    kind: DeviceKind


class _Coded(Protocol):
    code: Any
    device: str | None
    message: str
    since_utc: str


#: Pulse records per `pulses` reply (a follower asks again from where it is).
PULSES_PER_REPLY = 4096

Run = CaptureSession | MultiHostRun
"""What the slot runs: a take of this host's devices, or a take across hosts it coordinates."""

_D = TypeVar("_D", bound=_Device)
_V = TypeVar("_V")


def by_kind(devices: Iterable[_D], value: Callable[[_D], _V]) -> dict[DeviceKind, dict[str, _V]]:
    """`value` of each device, by device name, under its kind."""
    out: dict[DeviceKind, dict[str, _V]] = {}
    for d in devices:
        out.setdefault(d.kind, {})[d.name] = value(d)
    return out


def fault(f: _Coded) -> Fault:
    """A capture fault as the protocol sends it."""
    return Fault(code=f.code, device=f.device, message=f.message, since_utc=f.since_utc)


class RigSlot:
    """The daemon's take (at most one), recovery and device holder, and what they left."""

    def __init__(self, config: RigConfig) -> None:
        self.config = config
        self.lock = threading.RLock()
        """Guards every attribute below; hold it to read several consistently."""
        self.host = this_host(config)
        """This daemon's host on a multi-host rig (None: a one-host rig)."""
        self.session: Run | None = None
        self.state: DaemonState = "idle"
        self.last_take: TakeSummary | None = None
        self.takes_completed = 0
        self.idle_faults: list[Fault] = []
        """Faults that outlive the take (a full disk): shown until the next one starts."""
        self.recovered: list[dict[str, Any]] = []
        """What each recovery sealed or could not read, oldest first."""
        self.recovering = False
        self.holder: str | None = None
        self.last_feed: tuple[str, FeedState] | None = None
        """The last multi-host take's pulse records, for followers still fetching its tail."""
        """Who holds the devices outside a take (see `hold_devices`)."""

    # -- a take ------------------------------------------------------------------------
    def begin_capture(self, args: CaptureArgs) -> Run:
        """Claim the rig for a new take (quick; `busy` if one runs)."""
        if self.host is not None and self.host != self.config.coordinator:
            coord = self.config.coordinator
            raise RequestError(
                "config_error",
                f"this daemon is host {self.host} of a multi-host rig; takes start on the coordinator, "
                f"host {coord} ({self.config.hosts[coord].control if coord else '?'})",
            )
        return self._claim(lambda: self._new_run(args))

    def begin_part(self, args: CapturePartArgs) -> Run:
        """Claim the rig for this host's part of a multi-host take (the coordinator asks)."""
        if self.host is None or self.host == self.config.coordinator:
            raise RequestError("config_error", "capture_part is for the follower hosts of a multi-host rig")
        return self._claim(lambda: self._new_part(args))

    def _claim(self, make: Callable[[], Run]) -> Run:
        self.reap()
        with self.lock:
            if self.session is not None:
                raise RequestError("busy", f"a take is already running: {self.session.path}")
            if self.recovering:
                raise RequestError("busy", "unfinished takes are being recovered; try again when done")
            if self.holder is not None:
                raise RequestError("busy", f"the devices are held by {self.holder}; try again when done")
            session = make()
            self.session = session
            self.state = "starting"
        return session

    def _new_run(self, args: CaptureArgs) -> Run:
        svc = self.config.service
        if self.host is None:
            return CaptureSession(
                self.config,
                svc.take_dir,
                duration_s=args.duration_s,
                label=args.label,
                reconnect_interval_s=svc.reconnect_interval_s,
            )
        from rigd.app.service.gathering import gather_part, join_parts

        return MultiHostRun(
            self.config,
            self.host,
            svc.take_dir,
            duration_s=args.duration_s,
            label=args.label,
            reconnect_interval_s=svc.reconnect_interval_s,
            gather=functools.partial(gather_part, self.config),
            join=join_parts,
        )

    def _new_part(self, args: CapturePartArgs) -> Run:
        from rigd.app.capture.remote_trigger import RemoteTrigger
        from rigd.app.service.host_links import CoordinatorFeed, HostLink
        from rigd.take.parts import part_name

        svc = self.config.service
        assert self.host is not None
        coord = self.config.coordinator
        assert coord is not None
        feed = CoordinatorFeed(HostLink(self.config, coord), args.stem)
        return CaptureSession(
            self.config.for_host(self.host),
            svc.take_dir,
            duration_s=args.duration_s,
            path=svc.take_dir / part_name(args.stem, self.host),
            label=args.label,
            reconnect_interval_s=svc.reconnect_interval_s,
            open_trigger=lambda: RemoteTrigger(feed, spec=f"rigd-host://{coord}/{args.stem}"),
        )

    def pulses(self, args: PulsesArgs) -> dict[str, Any]:
        """The running take's pulse records for a follower host (`RemoteTrigger`)."""
        from rigd.app.service.host_links import feed_reply

        with self.lock:
            session = self.session
            last = self.last_feed
        if session is not None and Path(session.path).stem == args.stem:
            state = session.pulse_feed(args.since)
        elif last is not None and last[0] == args.stem:  # it ended: a follower fetches the tail
            final = last[1]
            keep = final.index >= args.since
            host_ns = None if final.host_ns is None else final.host_ns[keep]
            # No clock reading: the take's host clock went with its trigger, and the one taken
            # at its end is not "now" (a follower's clock offset must not learn from it).
            state = replace(
                final, index=final.index[keep], t_us=final.t_us[keep], host_ns=host_ns, now_ns=None
            )
        else:
            raise RequestError("not_capturing", f"take {args.stem} is not this daemon's running take")
        return feed_reply(state, PULSES_PER_REPLY)

    def start_capture(self, session: Run, args: CaptureArgs | CapturePartArgs) -> dict[str, Any]:
        """Open the devices and start the trigger (slow on real hardware)."""
        try:
            path = session.start()
        except BaseException:
            self.reap()
            raise
        with self.lock:
            if self.state == "starting":
                self.state = "capturing"
        log.info("take %s started (%s)", path, f"{args.duration_s} s" if args.duration_s else "until stopped")
        return {"take": str(path), "pulses_total": session.n_pulses}

    def stop(self, reason: str) -> dict[str, Any]:
        """Ask the running take to stop (it is sealed in the background)."""
        self.reap()
        with self.lock:
            session = self.session
            if session is None:
                raise RequestError("not_capturing", "no take is running")
            self.state = "stopping"
        session.request_stop(reason)
        return {"take": str(session.path), "stopping": True}

    def running(self) -> bool:
        with self.lock:
            return self.session is not None and not self.session.done

    def current_session(self) -> CaptureSession | None:
        with self.lock:
            session = self.session
        return session.local if isinstance(session, MultiHostRun) else session

    def hosts(self) -> list[HostTelemetry]:
        """The other hosts as the running multi-host take last reached them."""
        with self.lock:
            session = self.session
        return session.hosts() if isinstance(session, MultiHostRun) else []

    def finish(self, reason: str) -> None:
        """Stop the running take in a hurry and wait until it is sealed (the daemon is going)."""
        with self.lock:
            session = self.session
        if session is None:
            return
        if not session.done:
            sdnotify.notify("STATUS=finalizing the running take", "EXTEND_TIMEOUT_USEC=120000000")
            # The daemon is going away (a signal, a shutdown, a dead control loop): the stop's waits
            # end at writer.stop_backlog_s of wall-clock time, on virtual time too.
            session.request_stop(reason, hurry=True)
        try:
            session.wait()
        except BaseException as exc:  # noqa: BLE001 - summarized into last_take
            log.error("take %s ended with an error: %s", session.path, exc)
        self.reap()

    def reap(self) -> None:
        """Turn a finished session into `last_take` and go back to idle."""
        with self.lock:
            session = self.session
            if session is None or not session.done:
                return
            self.session = None
            self.state = "idle"
            self.takes_completed += 1
            if isinstance(session, MultiHostRun):
                self.last_feed = (Path(session.path).stem, session.pulse_feed(0))
            snap = session.snapshot()
            self.last_take = _summary(session, snap)
            self.idle_faults = [fault(f) for f in snap.faults if f.code in ("disk_full", "disk_low")]
        log.info("take %s: %s", self.last_take.path, self.last_take.status)
        _release_memory()

    # -- the devices, held outside a take ----------------------------------------------
    def hold_devices(self, holder: str) -> None:
        """Keep takes from starting while something else (a guided calibration) uses the devices;
        `busy` when a take runs or another holder has them. `release_devices` gives them back."""
        self.reap()
        with self.lock:
            if self.session is not None:
                raise RequestError("busy", f"a take is running: {self.session.path}")
            if self.holder is not None:
                raise RequestError("busy", f"the devices are held by {self.holder}")
            self.holder = holder

    def release_devices(self) -> None:
        with self.lock:
            self.holder = None

    # -- recovery ----------------------------------------------------------------------
    def claim_recovery(self) -> Callable[[], dict[str, Any]]:
        """Claim the rig for a recovery (`busy` while a take or another recovery runs); the
        job returned runs it and gives the rig back."""
        with self.lock:
            if self.session is not None:
                raise RequestError("busy", "not while a take is running")
            if self.recovering:
                raise RequestError("busy", "a recovery is already running")
            self.recovering = True
        return self._run_recovery

    def _run_recovery(self) -> dict[str, Any]:
        try:
            before = len(self.recovered)
            self.recover()
            return {"recovered": self.recovered[before:]}
        finally:
            with self.lock:
                self.recovering = False

    def recover(self) -> None:
        """Seal unfinished takes in take_dir. A file that cannot be read is reported and moved
        to take_dir/unreadable/ (kept); it never stops the daemon from starting and serving."""
        from rigd.take.recover_dir import log_problems, recover_dir

        take_dir = self.config.service.take_dir

        def sealing(path: Path) -> None:
            log.warning("take %s was left unfinished; checking and sealing it", path)
            sdnotify.notify(f"STATUS=sealing {path.name}", "EXTEND_TIMEOUT_USEC=120000000")

        try:
            results = recover_dir(take_dir, move_unreadable=True, before_each=sealing)
        except TakeError as exc:  # the directory itself cannot be listed
            log.error("recovery skipped: %s", exc)
            self.recovered.append({"path": str(take_dir), "error": str(exc)})
            return
        log_problems(results)
        self.recovered.extend(r.model_dump(mode="json") for r in results)


def _summary(session: Run, snap: SessionSnapshot) -> TakeSummary:
    """What the telemetry says about a take that ended."""
    res = session.result
    if res is not None:
        rep = res.report
        verdict = take_verdict("complete", rep, res.frames, res.events)
        return TakeSummary(
            path=str(res.path),
            status="complete",
            verdict=verdict.verdict,
            verdict_reasons=verdict.reasons,
            frames=res.frames,
            events=res.events,
            bytes_written=res.bytes_written,
            losses=rep.losses,
            warnings=rep.warnings,
            residual_rms_us={k: d.residual_rms_us for k, d in rep.devices.items()},
            end_reason=res.end_reason or None,
        )
    err = session.error
    totals = by_kind(snap.devices, lambda d: d.total)
    return TakeSummary(
        path=str(session.path),
        status="failed",
        verdict="failed",
        verdict_reasons=[f"{type(err).__name__}: {err}" if err else "unknown"],
        frames=totals.get("rgb_camera", {}),
        events=totals.get("event_sensor", {}),
        bytes_written=snap.bytes_written,
        losses=[],
        warnings=[],
        residual_rms_us={},
        error=f"{type(err).__name__}: {err}" if err else "unknown",
    )


def _release_memory() -> None:
    """Give the heap a take's buffers used back to the OS between takes.

    Frames and event batches are allocated on several acquisition threads; glibc keeps
    freed memory in per-thread arenas, so without this the daemon's resident size ratchets
    up with every take although nothing is alive (measured with bench/soak.py)."""
    gc.collect()
    try:
        libc = ctypes.CDLL(None)
        trim = libc.malloc_trim
    except (OSError, AttributeError):  # not glibc: nothing to do
        return
    trim(0)
