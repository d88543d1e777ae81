"""Reaching the other hosts of a multi-host rig: a control client per host, and the pulse feed.

Every host's daemon is reached at its `hosts.<name>.control` endpoint, with CurveZMQ keys when
the config names them (beyond loopback the daemon refuses to listen without them). The
coordinator arms, stops and reads the followers through these links; a follower fetches the
coordinator's pulse records through one (`CoordinatorFeed`, the `RemoteTrigger`'s source).
"""

from __future__ import annotations

import logging
import threading
from typing import Any

import numpy as np

from rigd.app.capture.remote_trigger import FeedState
from rigd.app.config import RigConfig
from rigd.app.service.client import DaemonClient, DaemonRequestError, DaemonUnavailableError
from rigd.core.errors import ConfigError, DeviceError, RigdError

log = logging.getLogger(__name__)

#: Deadline of one request to another host (a status, a stop, a batch of pulse records).
REQUEST_TIMEOUT_S = 5.0


def this_host(config: RigConfig) -> str | None:
    """The daemon's host on a multi-host rig (`service.host`, `rigd serve --host`), else None."""
    if not config.hosts:
        return None
    host = config.service.host
    if host is None:
        raise ConfigError(
            f"service.host: rig {config.name!r} places devices on hosts ({', '.join(config.hosts)}); "
            "say which one this daemon is (rigd serve --host NAME)"
        )
    if host not in config.hosts:
        raise ConfigError(f"service.host: {host!r} is not one of the rig's hosts ({', '.join(config.hosts)})")
    return host


class HostLink:
    """Requests to one host's daemon; thread-safe (one client, one request at a time)."""

    def __init__(self, config: RigConfig, host: str, timeout_s: float = REQUEST_TIMEOUT_S) -> None:
        hc = config.hosts[host]
        self.host = host
        self.endpoint = hc.control
        self.name = f"host {host} ({hc.control})"
        self._client = DaemonClient(
            hc.control,
            timeout_s=timeout_s,
            server_public_key=hc.server_public_key,
            client_secret_key=hc.client_secret_key,
        )
        self._lock = threading.Lock()

    def call(self, cmd: str, *, timeout_s: float | None = None, **args: Any) -> dict[str, Any]:
        """One request; `DaemonUnavailableError` when the host does not answer in time,
        `DaemonRequestError` when it refuses."""
        with self._lock:
            return self._client.call(cmd, timeout_s=timeout_s, **args)

    def close(self) -> None:
        with self._lock:
            self._client.close()


class CoordinatorFeed:
    """A follower's source of pulse records: the coordinator's `pulses` command."""

    def __init__(self, link: HostLink, stem: str) -> None:
        self._link = link
        self._stem = stem
        self.name = link.name

    def fetch(self, since: int) -> FeedState:
        try:
            res = self._link.call("pulses", stem=self._stem, since=since)
        except (DaemonUnavailableError, DaemonRequestError) as exc:
            raise DeviceError(f"pulse records from {self.name}: {exc}") from exc
        except RigdError as exc:  # a reply that is not the protocol's
            raise DeviceError(f"pulse records from {self.name}: {exc}") from exc
        try:
            index = np.asarray(res["index"], np.int64)
            t_us = np.asarray(res["t_us"], np.int64)
            emitted, now_ns = res["emitted"], res["now_ns"]
            state = FeedState(
                index,
                t_us,
                bool(res["running"]),
                None if emitted is None else int(str(emitted)),
                int(str(res["clock_us"])),
                np.asarray(res["host_ns"], np.int64),
                None if now_ns is None else int(str(now_ns)),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise DeviceError(f"pulse records from {self.name}: malformed reply ({exc})") from exc
        if (
            index.ndim != 1
            or t_us.shape != index.shape
            or state.host_ns is None
            or state.host_ns.shape != index.shape
        ):
            raise DeviceError(f"pulse records from {self.name}: index, t_us and host_ns differ in length")
        return state


def feed_reply(state: FeedState, limit: int) -> dict[str, object]:
    """A `pulses` reply: at most `limit` records (the follower asks again from where it is)."""
    return {
        "index": state.index[:limit].tolist(),
        "t_us": state.t_us[:limit].tolist(),
        "running": state.running,
        "emitted": state.emitted,
        "clock_us": state.clock_us,
        "host_ns": [] if state.host_ns is None else state.host_ns[:limit].tolist(),
        "now_ns": state.now_ns,
    }
