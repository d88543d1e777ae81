"""Slow requests run on a bounded pool: a flood of `devices` makes no more threads than the
pool has, what the pool cannot queue is answered `busy` at once, and `ping`/`status` are
still answered from the control loop meanwhile."""

from __future__ import annotations

import json
import threading
import time
from typing import Any

import pytest
import zmq

import drivers.discovery
from rigd.app.service.daemon import POOL_QUEUE, POOL_WORKERS
from rigd.app.service.protocol import Reply

N_REQUESTS = 200


def _pool_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("control-worker")]


class _BlockedDiscovery:
    """`discover()` that blocks until released: every worker stays busy for the test."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.entered = 0
        self._lock = threading.Lock()

    def __call__(self) -> Any:
        with self._lock:
            self.entered += 1
        self.release.wait(60)
        return _Report()


class _Report:
    def to_dict(self) -> dict[str, Any]:
        return {"devices": []}


def _recv_replies(sock: zmq.Socket[bytes], want: int, timeout_s: float) -> list[Reply]:
    """Read replies from a DEALER until `want` came or the deadline passed."""
    out: list[Reply] = []
    deadline = time.monotonic() + timeout_s
    while len(out) < want and time.monotonic() < deadline:
        if sock.poll(100):
            frames = sock.recv_multipart()
            out.append(Reply.model_validate_json(frames[-1]))
    return out


@pytest.mark.parametrize("n_requests", [POOL_WORKERS + POOL_QUEUE + 1, N_REQUESTS])
def test_devices_flood_bounded_threads_busy_replies_ping_answers(
    start_daemon: Any, monkeypatch: pytest.MonkeyPatch, n_requests: int
) -> None:
    blocked = _BlockedDiscovery()
    monkeypatch.setattr(drivers.discovery, "discover", blocked)
    rd = start_daemon()
    others_before = threading.active_count() - len(_pool_threads())
    dealer: zmq.Socket[bytes] = zmq.Context.instance().socket(zmq.DEALER)
    dealer.setsockopt(zmq.LINGER, 0)
    dealer.connect(rd.config.service.control_endpoint)
    try:
        for i in range(n_requests):
            body = json.dumps({"v": 1, "id": f"d{i}", "cmd": "devices"}).encode()
            dealer.send_multipart([b"", body])
        # What the pool cannot hold is refused at once, while the discovery is still blocked.
        max_accepted = POOL_WORKERS + POOL_QUEUE
        early = _recv_replies(dealer, n_requests - max_accepted, timeout_s=30)
        assert len(early) == n_requests - max_accepted, [r.error for r in early]
        assert all(not r.ok and r.error is not None and r.error.code == "busy" for r in early), early
        assert all("try again" in (r.error.message if r.error else "") for r in early)
        # The control loop still answers, from its own thread.
        ping = rd.client.call("ping")
        assert ping["state"] == "idle"
        assert rd.client.call("status")["state"] == "idle"
        assert len(_pool_threads()) == POOL_WORKERS
        others = threading.active_count() - len(_pool_threads())
        assert others <= others_before, [t.name for t in threading.enumerate()]
        # Released: the accepted ones are all answered, with a result. (A few more than the
        # minimum may have been refused: the queue can fill before a worker takes its job.)
        blocked.release.set()
        late = _recv_replies(dealer, n_requests - len(early), timeout_s=30)
        replies = early + late
        assert len(replies) == n_requests
        assert {r.id for r in replies} == {f"d{i}" for i in range(n_requests)}
        ok = [r for r in replies if r.ok]
        busy = [r for r in replies if r.error is not None and r.error.code == "busy"]
        assert len(ok) + len(busy) == n_requests
        assert POOL_QUEUE <= len(ok) <= max_accepted
        assert all(r.result == {"devices": []} for r in ok)
        assert blocked.entered == len(ok)
    finally:
        blocked.release.set()
        dealer.close(linger=0)
    # The pool takes new work again once it has drained.
    assert rd.client.call("devices") == {"devices": []}
    assert len(_pool_threads()) == POOL_WORKERS


@pytest.mark.slow
def test_capture_not_refused_while_the_pool_is_full(
    start_daemon: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """capture has its own thread: a pool full of `devices` does not make it `busy`."""
    blocked = _BlockedDiscovery()
    monkeypatch.setattr(drivers.discovery, "discover", blocked)
    rd = start_daemon()
    dealer: zmq.Socket[bytes] = zmq.Context.instance().socket(zmq.DEALER)
    dealer.setsockopt(zmq.LINGER, 0)
    dealer.connect(rd.config.service.control_endpoint)
    try:
        n = POOL_WORKERS + POOL_QUEUE + 5
        for i in range(n):
            dealer.send_multipart([b"", json.dumps({"v": 1, "id": f"d{i}", "cmd": "devices"}).encode()])
        busy = _recv_replies(dealer, 5, timeout_s=30)
        assert [r.error.code for r in busy if r.error] == ["busy"] * 5
        res = rd.client.call("capture", timeout_s=60, duration_s=0.5)
        assert res["take"]
    finally:
        blocked.release.set()
        dealer.close(linger=0)
