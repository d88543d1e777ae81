"""A client found by its quick ping waits the normal deadline afterwards: a daemon that takes
more than the probe's second to answer (finalizing a take, compiling a kernel) is busy, not gone."""

from __future__ import annotations

import json
import socket
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import zmq

from rigd.app.service.client import DaemonClient, DaemonUnavailableError, find_daemon

#: Longer than the probe's deadline, well inside the calls' one.
SLOW_S = 1.6


def _serve(tmp_path: Path, slow: str) -> Iterator[str]:
    """A REP socket answering every command at once but `slow`, which it answers after SLOW_S (it
    waits on an event with that timeout, so nothing here depends on how busy the machine is but
    the bound)."""
    endpoint = f"ipc://{tmp_path}/control.sock"
    ctx = zmq.Context.instance()
    sock = ctx.socket(zmq.REP)
    sock.setsockopt(zmq.LINGER, 0)
    sock.bind(endpoint)
    done = threading.Event()

    def serve() -> None:
        poller = zmq.Poller()
        poller.register(sock, zmq.POLLIN)
        while not done.is_set():
            if not poller.poll(50):
                continue
            req = json.loads(sock.recv())
            if req["cmd"] == slow:
                done.wait(SLOW_S)
            sock.send(
                json.dumps(
                    {"v": req["v"], "id": req["id"], "ok": True, "result": {"cmd": req["cmd"]}}
                ).encode()
            )

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    yield endpoint
    done.set()
    t.join(5)
    sock.close()


@pytest.fixture
def slow_daemon(tmp_path: Path) -> Iterator[str]:
    """Answers `ping` at once and `status` after SLOW_S."""
    yield from _serve(tmp_path, "status")


@pytest.fixture
def slow_to_ping(tmp_path: Path) -> Iterator[str]:
    """A live daemon on a loaded host: answers `ping` after SLOW_S."""
    yield from _serve(tmp_path, "ping")


@pytest.mark.slow
def test_a_found_client_waits_longer_than_the_probe(slow_daemon: str) -> None:
    client = find_daemon(slow_daemon, timeout_s=1.0)
    assert client is not None
    with client:
        assert client.call("status") == {"cmd": "status"}


def test_a_short_call_deadline_still_gives_up(slow_daemon: str) -> None:
    client = find_daemon(slow_daemon, timeout_s=1.0, call_timeout_s=0.3)
    assert client is not None
    with client, pytest.raises(DaemonUnavailableError, match=r"within 0\.3 s"):
        client.call("status")


@pytest.mark.slow
def test_a_listening_daemon_slower_than_the_probe_is_found_not_reported_gone(slow_to_ping: str) -> None:
    """Its IPC socket accepts connections, so it is there: the ping gets the calls' deadline."""
    client = find_daemon(slow_to_ping, timeout_s=1.0)
    assert client is not None
    client.close()


def _no_ping(self: DaemonClient, *args: object, **kwargs: object) -> None:
    raise AssertionError("pinged an endpoint where nothing listens")


def test_a_stale_socket_file_is_no_daemon_without_a_ping(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A killed daemon leaves its socket file: nothing accepts on it, and that is known at once."""
    path = tmp_path / "control.sock"
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(path))
    stale.close()
    assert path.exists()
    (tmp_path / "file.sock").write_text("not a socket")
    monkeypatch.setattr(DaemonClient, "call", _no_ping)
    assert find_daemon(f"ipc://{path}", call_timeout_s=3600) is None
    assert find_daemon(f"ipc://{tmp_path / 'file.sock'}", call_timeout_s=3600) is None
    assert find_daemon(f"ipc://{tmp_path / 'none.sock'}", call_timeout_s=3600) is None
