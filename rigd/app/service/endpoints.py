"""Binding the daemon's sockets safely: owner-only IPC, loopback TCP, CurveZMQ for remote."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

from rigd.app.config import CurveConfig
from rigd.core.errors import ConfigError, RigdError
from rigd.core.private_dir import check_private_dir

log = logging.getLogger(__name__)


class DaemonRunningError(RigdError):
    """Another daemon already answers on the control endpoint."""


def ipc_path(endpoint: str) -> Path | None:
    return Path(endpoint.removeprefix("ipc://")) if endpoint.startswith("ipc://") else None


def prepare_ipc_dir(path: Path) -> None:
    """Create the socket's directory owner-only, or refuse one others can write into."""
    d = path.parent
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    check_private_dir(d, "service.control", "use a private directory (RIGD_RUNTIME_DIR) or chmod 700 it")


def secure_ipc_socket(path: Path) -> None:
    """After bind: only the owner may connect (group access is what systemd's unit grants)."""
    os.chmod(path, 0o600)


def start_authenticator(ctx: zmq.Context[zmq.Socket[bytes]], curve: CurveConfig) -> ThreadAuthenticator:
    """Accept CURVE clients whose public keys are in `authorized_keys_dir`."""
    if not curve.authorized_keys_dir.is_dir():
        raise ConfigError(
            f"service.curve.authorized_keys_dir: {curve.authorized_keys_dir} is not a directory"
        )
    auth = ThreadAuthenticator(ctx)
    auth.start()
    auth.configure_curve(domain="*", location=str(curve.authorized_keys_dir))
    return auth


def apply_server_curve(sock: zmq.Socket[bytes], curve: CurveConfig) -> None:
    try:
        public, secret = zmq.auth.load_certificate(str(curve.server_secret_key))
    except (OSError, ValueError) as exc:
        raise ConfigError(
            f"service.curve.server_secret_key: cannot load {curve.server_secret_key}: {exc}"
        ) from exc
    if secret is None:
        raise ConfigError(f"service.curve.server_secret_key: {curve.server_secret_key} holds no secret key")
    sock.curve_secretkey = secret
    sock.curve_publickey = public
    sock.curve_server = True


def bind(sock: zmq.Socket[bytes], endpoint: str, what: str) -> None:
    path = ipc_path(endpoint)
    if path is not None:
        prepare_ipc_dir(path)
        if path.exists():
            # A stale socket from a killed daemon; a live one was ruled out by the caller.
            log.warning("removing stale %s socket %s", what, path)
            path.unlink()
    try:
        sock.bind(endpoint)
    except zmq.ZMQError as exc:
        raise ConfigError(f"service.{what}: cannot bind {endpoint}: {exc}") from exc
    if path is not None:
        secure_ipc_socket(path)
    log.info("%s socket bound at %s", what, endpoint)
