"""A client found by its quick ping waits the normal deadline afterwards: a daemon that takes
more than the probe's second to answer (finalizing a take, compiling a kernel) is busy, not gone."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import zmq

from rigd.app.service.client import DaemonUnavailableError, find_daemon

#: Longer than the probe's deadline, well inside the calls' one.
SLOW_S = 1.6


@pytest.fixture
def slow_daemon(tmp_path: Path) -> Iterator[str]:
    """A REP socket answering `ping` at once and `status` only after SLOW_S (it waits on an
    event with that timeout, so nothing here depends on how busy the machine is but the bound)."""
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
            if req["cmd"] == "status":
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
