"""Talking to a running `rigd serve`: one request, one reply, a deadline on each.

A REQ socket that missed a reply is unusable, so a timed-out client closes it and opens a
fresh one on the next call (ZeroMQ's "lazy pirate" pattern).
"""

from __future__ import annotations

import errno
import json
import logging
import os
import socket
import uuid
from pathlib import Path
from typing import Any, Self

import zmq
import zmq.auth

from rigd.app.service.endpoints import ipc_path
from rigd.app.service.protocol import PROTOCOL_VERSION, ErrorInfo, Reply
from rigd.core.errors import RigdError

log = logging.getLogger(__name__)


class DaemonUnavailableError(RigdError):
    """No daemon answered at the endpoint in time."""


class DaemonRequestError(RigdError):
    """The daemon answered with a structured error."""

    def __init__(self, error: ErrorInfo) -> None:
        where = f" ({error.field})" if error.field else ""
        super().__init__(f"{error.code}{where}: {error.message}")
        self.error = error


class DaemonClient:
    """Synchronous client; not thread-safe (one per thread)."""

    def __init__(
        self,
        endpoint: str,
        *,
        timeout_s: float = 5.0,
        server_public_key: Path | None = None,
        client_secret_key: Path | None = None,
    ) -> None:
        self.endpoint = endpoint
        self.timeout_s = timeout_s
        self._curve = (server_public_key, client_secret_key)
        self._ctx: zmq.Context[zmq.Socket[bytes]] = zmq.Context.instance()
        self._sock: zmq.Socket[bytes] | None = None

    def _socket(self) -> zmq.Socket[bytes]:
        if self._sock is None:
            sock = self._ctx.socket(zmq.REQ)
            sock.setsockopt(zmq.LINGER, 0)
            sock.setsockopt(zmq.SNDTIMEO, int(self.timeout_s * 1000))
            server_pub, client_sec = self._curve
            if server_pub is not None and client_sec is not None:
                public, secret = zmq.auth.load_certificate(str(client_sec))
                if secret is None:
                    raise RigdError(f"{client_sec} holds no secret key")
                sock.curve_publickey, sock.curve_secretkey = public, secret
                sock.curve_serverkey = zmq.auth.load_certificate(str(server_pub))[0]
            sock.connect(self.endpoint)
            self._sock = sock
        return self._sock

    def set_timeout(self, timeout_s: float) -> None:
        """The deadline of later calls (sending and waiting for the reply)."""
        self.timeout_s = timeout_s
        if self._sock is not None:
            self._sock.setsockopt(zmq.SNDTIMEO, int(timeout_s * 1000))

    def send_raw(self, payload: bytes, timeout_s: float | None = None) -> bytes:
        """Send bytes as they are and return the reply's JSON frame (for tests and fuzzing)."""
        return self._exchange(payload, timeout_s)[0]

    def _exchange(self, payload: bytes, timeout_s: float | None) -> list[bytes]:
        """One request, and every frame of its reply (a binary take_read has two)."""
        sock = self._socket()
        wait_s = self.timeout_s if timeout_s is None else timeout_s
        try:
            sock.setsockopt(zmq.RCVTIMEO, int(wait_s * 1000))
            sock.send(payload)
            return sock.recv_multipart()
        except zmq.Again:
            self._reset()
            raise DaemonUnavailableError(
                f"no reply from the daemon at {self.endpoint} within {wait_s:g} s"
            ) from None

    def call(self, cmd: str, *, timeout_s: float | None = None, **args: Any) -> dict[str, Any]:
        """Run one command; returns its result or raises `DaemonRequestError`.

        `timeout_s` overrides the client's deadline for this call (`capture` replies once the
        devices are open, which takes seconds on real hardware).
        """
        return self.call_with_payload(cmd, timeout_s=timeout_s, **args)[0]

    def call_with_payload(
        self, cmd: str, *, timeout_s: float | None = None, **args: Any
    ) -> tuple[dict[str, Any], bytes | None]:
        """`call`, and the bytes of the reply's second frame (None when it has none)."""
        req_id = uuid.uuid4().hex[:12]
        body = json.dumps({"v": PROTOCOL_VERSION, "id": req_id, "cmd": cmd, "args": args}).encode()
        frames = self._exchange(body, timeout_s)
        reply = Reply.model_validate_json(frames[0])
        if reply.id != req_id:
            raise RigdError(f"daemon at {self.endpoint} answered request {reply.id!r}, expected {req_id!r}")
        if not reply.ok:
            assert reply.error is not None
            raise DaemonRequestError(reply.error)
        if len(frames) > 2:
            raise RigdError(f"daemon at {self.endpoint} answered with {len(frames)} frames (at most 2)")
        return reply.result or {}, frames[1] if len(frames) == 2 else None

    def _reset(self) -> None:
        if self._sock is not None:
            self._sock.close(linger=0)
            self._sock = None

    def close(self) -> None:
        self._reset()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class DaemonAccessError(RigdError):
    """The daemon's control socket exists but this user may not connect to it."""


#: Key files a command line presents to a daemon behind CurveZMQ (`rigd keys` writes them).
SERVER_KEY_ENV = "RIGD_SERVER_PUBLIC_KEY"
CLIENT_KEY_ENV = "RIGD_CLIENT_SECRET_KEY"


def curve_keys_from_env() -> tuple[Path | None, Path | None]:
    """The daemon's public key and this side's secret key named by the environment (or None)."""
    server, client = os.environ.get(SERVER_KEY_ENV), os.environ.get(CLIENT_KEY_ENV)
    return (Path(server) if server else None), (Path(client) if client else None)


def find_daemon(endpoint: str, timeout_s: float = 1.0, call_timeout_s: float = 5.0) -> DaemonClient | None:
    """A client for the daemon at `endpoint` if one answers a ping, else None. The client's
    later calls wait up to `call_timeout_s`: a daemon busy finalizing a take may take more than
    a second to answer, and that is not a daemon gone.

    On IPC the socket file says at once whether a daemon listens (none, or a stale file a killed
    daemon left, refuses the connection), so a listening one gets `call_timeout_s` to answer the
    ping: on a loaded host a live daemon answered a 1 s probe too late and was reported absent.
    Elsewhere (TCP) the ping must come within `timeout_s`."""
    path = ipc_path(endpoint)
    if path is not None:
        if not _ipc_listening(path):
            return None
        timeout_s = max(timeout_s, call_timeout_s)
    server_key, client_key = curve_keys_from_env() if path is None else (None, None)
    client = DaemonClient(
        endpoint, timeout_s=timeout_s, server_public_key=server_key, client_secret_key=client_key
    )
    try:
        client.call("ping")
    except DaemonUnavailableError:
        client.close()
        return None
    except DaemonRequestError as exc:
        client.close()
        raise RigdError(f"the daemon at {endpoint} refused ping: {exc}") from exc
    client.set_timeout(call_timeout_s)
    return client


def _ipc_listening(path: Path) -> bool:
    """Whether something accepts connections on the Unix socket at `path` (no file, a stale
    one, or a file that is no socket: False)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        try:
            probe.connect(str(path))
        except (FileNotFoundError, ConnectionRefusedError, NotADirectoryError):
            return False
        except PermissionError as exc:  # the socket, or its 0700 directory, is another user's
            raise DaemonAccessError(
                f"the daemon's control socket {path} is not open to this user (permission denied): "
                "run the command as the daemon's user (e.g. `sudo -u rigd rigd ...`)"
            ) from exc
        except OSError as exc:
            if exc.errno in (errno.ENOTSOCK, errno.ECONNREFUSED, errno.ENOENT):
                return False
            raise
    return True
