"""The coordinator's take on a multi-host rig: arm every host, run the box, stop, gather, join.

The coordinator (the host that owns the trigger box) runs its own devices in a normal
`CaptureSession` whose take is its part. Before its box starts, every other host is armed
(`capture_part`): it opens its devices and records them into its own part on the coordinator's
pulse records (`RemoteTrigger`). A host that does not answer then fails the start in one line,
before any pulse. Once the box has stopped, the hosts are told to stop (a counted take stops by
itself), their parts are sealed where they were written, copied here (`take_read`, checked by
size and SHA-256) and joined into `<stem>.h5`, which reads as any take. A host that died or
stopped answering costs only its devices: the joined take is `degraded` naming them, and
`rigd recover` on that host plus `rigd takes gather` here completes it later (docs/multi-host.md).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from rigd.app.capture import CaptureSession, SessionSnapshot
from rigd.app.capture.remote_trigger import FeedState
from rigd.app.capture.request import new_take_path
from rigd.app.capture.results import CaptureResult
from rigd.app.config import RigConfig
from rigd.app.service.client import DaemonRequestError, DaemonUnavailableError
from rigd.app.service.host_links import REQUEST_TIMEOUT_S, HostLink
from rigd.app.service.protocol import HostTelemetry
from rigd.core.errors import RigdError, TakeError
from rigd.take.parts import part_name

log = logging.getLogger(__name__)

#: How long a host may take to open its devices and answer `capture_part`.
ARM_TIMEOUT_S = 60.0
#: A host that answers nothing for this long (wall seconds) is lost: its part is left to recover.
HOST_LOST_S = 10.0
#: How often the coordinator asks each host how it is (status, and whether its part is sealed).
POLL_S = 0.5

Gather = Callable[[str, str, Path], Path]
"""Copies a host's part (host, file name) into a directory and returns where it is."""
Join = Callable[[Path, Path, dict[str, tuple[Path | None, tuple[str, ...]]], dict[str, str]], None]
"""Writes the joined take: (out, coordinator's part, host -> (part or None, devices), host -> why missing)."""


class MultiHostSession:
    """One take across hosts; the daemon's rig slot runs it as it runs a `CaptureSession`."""

    def __init__(
        self,
        config: RigConfig,
        host: str,
        take_dir: Path,
        *,
        duration_s: float | None,
        label: str | None,
        reconnect_interval_s: float | None,
        gather: Gather,
        join: Join,
    ) -> None:
        self.config = config
        self.host = host
        self.stem = new_take_path(take_dir, config.name, label).stem
        self.path = take_dir / f"{self.stem}.h5"
        self._take_dir = take_dir
        self._duration_s = duration_s
        self._label = label
        self.local = CaptureSession(
            config.for_host(host),
            take_dir,
            duration_s=duration_s,
            path=take_dir / part_name(self.stem, host),
            label=label,
            reconnect_interval_s=reconnect_interval_s,
        )
        self.n_pulses = self.local.n_pulses
        self.followers = [h for h in config.host_names() if h != host]
        self._links = {h: HostLink(config, h) for h in self.followers}
        self._gather = gather
        self._join = join
        self._lock = threading.Lock()
        self._hosts: dict[str, HostTelemetry] = {
            h: HostTelemetry(
                name=h, endpoint=self._links[h].endpoint, reachable=True, devices=config.devices_on(h)
            )
            for h in self.followers
        }
        self._last_answer = {h: time.monotonic() for h in self.followers}
        self._done = threading.Event()
        self._result: CaptureResult | None = None
        self._error: BaseException | None = None
        self._state = "new"
        self._thread: threading.Thread | None = None
        self._armed: list[str] = []

    # -- the surface the rig slot uses -----------------------------------------------------
    @property
    def state(self) -> str:
        return self._state

    @property
    def done(self) -> bool:
        return self._done.is_set()

    @property
    def error(self) -> BaseException | None:
        return self._error

    @property
    def result(self) -> CaptureResult | None:
        return self._result

    def snapshot(self) -> SessionSnapshot:
        return self.local.snapshot()

    def hosts(self) -> list[HostTelemetry]:
        with self._lock:
            return list(self._hosts.values())

    def request_stop(self, reason: str = "stop requested", *, hurry: bool = False) -> None:
        self.local.request_stop(reason, hurry=hurry)

    def wait(self, timeout: float | None = None) -> CaptureResult | None:
        if not self._done.wait(timeout):
            return None
        if self._error is not None:
            raise self._error
        return self._result

    def pulse_feed(self, since: int) -> FeedState:
        return self.local.pulse_feed(since)

    def start(self) -> Path:
        """Open this host's devices, arm every other host (in parallel), then start the box: a
        host that cannot be armed fails the start before any pulse."""
        self._state = "starting"
        try:
            self.local.start(before_pulses=self._arm_all)
        except BaseException as exc:
            self._failed(exc)
            self._disarm(self._armed, f"the take did not start: {exc}")
            self._end()
            raise
        self._state = "capturing"
        self._thread = threading.Thread(target=self._run, name="multihost", daemon=True)
        self._thread.start()
        return self.path

    def _arm_all(self) -> None:
        failures: list[str] = []
        with ThreadPoolExecutor(max(1, len(self.followers))) as pool:
            futures = {h: pool.submit(self._arm, h) for h in self.followers}
            for h, fut in futures.items():
                try:
                    fut.result()
                    self._armed.append(h)
                except (DaemonUnavailableError, DaemonRequestError, RigdError) as exc:
                    failures.append(f"{self._links[h].name} did not arm: {exc}")
        if failures:
            raise TakeError("; ".join(failures) + "; no pulse was sent")

    # -- internals -------------------------------------------------------------------------
    def _failed(self, exc: BaseException) -> None:
        """The take did not start: the hosts armed so far learn that the box sent no pulse."""
        self._error = exc
        self._state = "failed"

    def _end(self) -> None:
        for link in self._links.values():
            link.close()
        self._done.set()

    def _arm(self, host: str) -> None:
        link = self._links[host]
        theirs = link.call("config", timeout_s=REQUEST_TIMEOUT_S)  # a host that is not there: fails here
        ours = self.config.model_dump(mode="json")
        differ = sorted(k for k in set(ours) | set(theirs) if k != "service" and ours.get(k) != theirs.get(k))
        if differ:
            raise TakeError(
                f"its rig config differs from this host's in {', '.join(differ)} (every host runs the "
                "same rig config; only [service] may differ)"
            )
        link.call(
            "capture_part",
            timeout_s=ARM_TIMEOUT_S,
            stem=self.stem,
            duration_s=self._duration_s,
            label=self._label,
        )
        log.info("take %s: host %s armed", self.stem, host)

    def _disarm(self, hosts: list[str], reason: str) -> None:
        for h in hosts:
            try:
                self._links[h].call("stop", reason=reason[:200])
            except (DaemonUnavailableError, DaemonRequestError) as exc:
                log.warning("take %s: host %s: %s", self.stem, h, exc)

    def _run(self) -> None:
        try:
            self._follow_local()
            parts = self._collect_parts()
            self._state = "joining"
            self._join_parts(parts)
            self._state = "done"
        except BaseException as exc:  # noqa: BLE001 - kept for wait() and the slot's summary
            log.error("take %s failed: %s: %s", self.path, type(exc).__name__, exc)
            self._error = exc
            self._state = "failed"
        finally:
            self._end()

    def _follow_local(self) -> None:
        """Watch the hosts while this host's take runs; tell them to stop once the box has."""
        told = False
        while not self.local.done:
            self._poll_hosts()
            if not told and self.local.pulse_feed(1 << 40).emitted is not None:
                self._disarm(self.followers, "the coordinator's box stopped")
                told = True
            self.local.wait(POLL_S)
        if not told:
            self._disarm(self.followers, "the coordinator's take ended")

    def _poll_hosts(self) -> None:
        now = time.monotonic()
        for h in self.followers:
            try:
                t = self._links[h].call("status", timeout_s=2.0)
            except (DaemonUnavailableError, DaemonRequestError) as exc:
                quiet = now - self._last_answer[h]
                with self._lock:
                    self._hosts[h] = self._hosts[h].model_copy(
                        update={"reachable": False, "message": f"no answer for {quiet:.0f} s: {exc}"}
                    )
                continue
            self._last_answer[h] = now
            faults = t.get("faults") or []
            with self._lock:
                self._hosts[h] = self._hosts[h].model_copy(
                    update={
                        "reachable": True,
                        "state": t.get("state"),
                        "take": t.get("take"),
                        "pulses": int(t.get("pulses") or 0),
                        "message": faults[0]["message"] if faults else None,
                    }
                )

    def _collect_parts(self) -> dict[str, tuple[Path | None, str | None]]:
        """Each host's part here (copied), or why it is not: sealed where it was written first.
        The hosts at once: each part comes from its own host's disk and network link."""
        if not self.followers:
            return {}
        with ThreadPoolExecutor(len(self.followers), thread_name_prefix="collect") as pool:
            futures = {h: pool.submit(self._collect_part, h) for h in self.followers}
            return {h: fut.result() for h, fut in futures.items()}

    def _collect_part(self, h: str) -> tuple[Path | None, str | None]:
        name = part_name(self.stem, h)
        why = self._wait_sealed(h, name)
        if why is not None:
            return None, why
        try:
            return self._gather(h, name, self._take_dir), None
        except (DaemonUnavailableError, DaemonRequestError, RigdError, OSError) as exc:
            return None, f"its part {name} could not be copied: {exc}"

    def _wait_sealed(self, host: str, name: str) -> str | None:
        """Until `host` reports its part sealed; None then, else why it is missing."""
        link = self._links[host]
        last_answer = time.monotonic()
        while True:
            try:
                t = link.call("status", timeout_s=2.0)
            except (DaemonUnavailableError, DaemonRequestError) as exc:
                if time.monotonic() - last_answer > HOST_LOST_S:
                    return (
                        f"{link.name} stopped answering ({exc}); its part {name} is on that host: "
                        "`rigd recover` there, then `rigd takes gather` here completes the take"
                    )
                time.sleep(POLL_S)
                continue
            last_answer = time.monotonic()
            last = t.get("last_take") or {}
            if t.get("take") is None or not str(t.get("take")).endswith(name):
                if str(last.get("path", "")).endswith(name):
                    if last.get("status") == "failed":
                        return f"{link.name}: its part {name} failed: {last.get('error')}"
                    return None
                return f"{link.name} is not recording {name} (it was not armed, or restarted)"
            time.sleep(POLL_S)

    def _join_parts(self, parts: dict[str, tuple[Path | None, str | None]]) -> None:
        local_error: BaseException | None = None
        try:
            self.local.wait()
        except BaseException as exc:  # noqa: BLE001 - the hosts' parts are still joined
            local_error = exc
        if local_error is not None and not self.local.path.exists():
            raise local_error
        hosts: dict[str, tuple[Path | None, tuple[str, ...]]] = {
            self.host: (self.local.path, tuple(self.config.devices_on(self.host)))
        }
        hosts.update({h: (p, tuple(self.config.devices_on(h))) for h, (p, _) in parts.items()})
        missing = {h: why for h, (_, why) in parts.items() if why is not None}
        self._join(self.path, self.local.path, hosts, missing)
        self._result = joined_result(self.path, self.local.result)
        if local_error is not None:
            raise local_error


def joined_result(path: Path, local: CaptureResult | None) -> CaptureResult:
    """The summary of a joined take, read back from it (what the client and telemetry show)."""
    from rigd.take import Take

    with Take(path) as take:
        report = take.sync_report
        frames = {name: len(take.camera(name)) for name in take.cameras}
        events = {name: len(take.sensor(name)) for name in take.event_sensors}
    if report is None:
        raise TakeError(f"{path}: the joined take has no sync report")
    size = sum(p.stat().st_size for p in path.parent.glob(f"{path.stem}.*part.h5")) + path.stat().st_size
    return CaptureResult(
        path,
        report,
        frames,
        events,
        size,
        local.wall_s if local is not None else 0.0,
        local.capture_s if local is not None else 0.0,
        end_reason=local.end_reason if local is not None else "",
    )
