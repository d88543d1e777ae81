"""sd_notify against a real AF_UNIX datagram socket, as systemd listens."""

from __future__ import annotations

import logging
import os
import socket
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from rigd.app.service import sdnotify


@pytest.fixture
def listener(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[socket.socket]:
    path = tmp_path / "notify.sock"
    if len(str(path)) >= 100:  # sun_path is 108 bytes
        pytest.skip(f"tmp path too long for an AF_UNIX socket: {path}")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(str(path))
        sock.settimeout(2)
        monkeypatch.setenv("NOTIFY_SOCKET", str(path))
        yield sock


def test_sends_fields_in_one_datagram(listener: socket.socket) -> None:
    assert sdnotify.notify("READY=1", "STATUS=idle", f"MAINPID={os.getpid()}")
    assert listener.recv(4096) == f"READY=1\nSTATUS=idle\nMAINPID={os.getpid()}".encode()


def test_newlines_in_a_field_do_not_split_it(listener: socket.socket) -> None:
    assert sdnotify.notify("STATUS=error: device failed\ntraceback line")
    assert listener.recv(4096) == b"STATUS=error: device failed traceback line"


def test_watchdog_and_stopping(listener: socket.socket) -> None:
    assert sdnotify.notify("WATCHDOG=1")
    assert sdnotify.notify("STOPPING=1")
    assert listener.recv(4096) == b"WATCHDOG=1"
    assert listener.recv(4096) == b"STOPPING=1"


def test_abstract_socket(monkeypatch: pytest.MonkeyPatch) -> None:
    name = f"rigd-test-{uuid.uuid4().hex}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(b"\0" + name.encode())
        sock.settimeout(2)
        monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
        assert sdnotify.notify("READY=1")
        assert sock.recv(4096) == b"READY=1"


def test_not_under_systemd_is_a_quiet_no_op(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    before = sdnotify.failures()
    with caplog.at_level(logging.DEBUG, logger="rigd.app.service.sdnotify"):
        assert sdnotify.notify("READY=1") is False
    assert sdnotify.failures() == before
    assert [r.levelno for r in caplog.records] == [logging.DEBUG]


@pytest.mark.parametrize("address", ["relative/notify.sock", "/nonexistent/rigd/notify.sock"])
def test_send_error_is_logged_and_counted_not_raised(
    address: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setenv("NOTIFY_SOCKET", address)
    before = sdnotify.failures()
    with caplog.at_level(logging.WARNING, logger="rigd.app.service.sdnotify"):
        assert sdnotify.notify("WATCHDOG=1") is False
    assert sdnotify.failures() == before + 1
    assert any("WATCHDOG=1" in r.getMessage() and r.levelno == logging.WARNING for r in caplog.records)


def test_systemd_gone_after_start(listener: socket.socket, tmp_path: Path) -> None:
    """The socket disappears (systemd restarted): a warning, no exception."""
    assert sdnotify.notify("READY=1")
    (tmp_path / "notify.sock").unlink()
    before = sdnotify.failures()
    assert sdnotify.notify("WATCHDOG=1") is False
    assert sdnotify.failures() == before + 1


def test_no_fields_is_a_programming_error() -> None:
    with pytest.raises(ValueError, match="at least one field"):
        sdnotify.notify()


def test_watchdog_interval(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    assert sdnotify.watchdog_interval_s() is None

    monkeypatch.setenv("WATCHDOG_USEC", "10000000")  # WatchdogSec=10
    assert sdnotify.watchdog_interval_s() == pytest.approx(5.0)

    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    assert sdnotify.watchdog_interval_s() == pytest.approx(5.0)

    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid() + 1))  # inherited from a parent
    assert sdnotify.watchdog_interval_s() is None


@pytest.mark.parametrize(("usec", "pid"), [("abc", None), ("0", None), ("-5", None), ("1000", "x")])
def test_watchdog_interval_invalid(
    usec: str, pid: str | None, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setenv("WATCHDOG_USEC", usec)
    if pid is None:
        monkeypatch.delenv("WATCHDOG_PID", raising=False)
    else:
        monkeypatch.setenv("WATCHDOG_PID", pid)
    with caplog.at_level(logging.WARNING, logger="rigd.app.service.sdnotify"):
        assert sdnotify.watchdog_interval_s() is None
    assert caplog.records
