"""The two ends of the simulated trigger cable (`firmware_sim.cable`): its wire format, the lead
that listens and the followers that connect.

Frames on the Unix stream socket: a header `<BI` (type, body length) and the body. The
handshake is JSON (HELLO from the follower, WELCOME or REFUSE from the lead); the rest is
fixed binary records: EDGE and ADVANCE from the lead, STATE from the follower, BYE from either
on a clean close. Each end writes through a queue drained by its own thread, so no clock lock
ever waits on the other process.

Sequence numbers make "delivered before the advance" hold without a lock across processes:
the lead numbers every EDGE and ADVANCE it sends a follower, and counts the follower idle only
once a STATE acknowledges the last of them and says nothing holds time there.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import json
import logging
import math
import os
import queue
import socket
import stat
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import IO, TYPE_CHECKING, Any

from firmware_sim.cable import CableParams, check_private_dir
from firmware_sim.clock import VirtualClock, VirtualHostClock
from firmware_sim.world import Edge
from rigd.core.errors import ConfigError, DeviceError

if TYPE_CHECKING:
    from firmware_sim.world import SimWorld

log = logging.getLogger(__name__)

VERSION = 1
HELLO, WELCOME, REFUSE, EDGE, ADVANCE, STATE, BYE = range(1, 8)
_NAMES = dict(enumerate(("HELLO", "WELCOME", "REFUSE", "EDGE", "ADVANCE", "STATE", "BYE"), start=1))
_HEADER = struct.Struct("<BI")
_EDGE = struct.Struct("<QBdq")  # seq, rising, true_us, pulse_index
_ADVANCE = struct.Struct("<Qd")  # seq, now_us
_STATE = struct.Struct("<QBd")  # acknowledged seq, idle, next deadline (inf: none)
_SIZES = {EDGE: _EDGE.size, ADVANCE: _ADVANCE.size, STATE: _STATE.size, BYE: 0}
_MAX_JSON = 65536
#: How long (wall seconds) a handshake may take once connected.
HANDSHAKE_S = 5.0
#: How often (wall seconds) a follower tries again to reach a lead that does not listen yet.
_RETRY_S = 0.05


def frame(kind: int, body: bytes = b"") -> bytes:
    return _HEADER.pack(kind, len(body)) + body


def _json_frame(kind: int, obj: dict[str, Any]) -> bytes:
    return frame(kind, json.dumps(obj).encode())


def read_frame(stream: IO[bytes], peer: str) -> tuple[int, bytes] | None:
    """The next frame, or None at a clean end of stream; DeviceError on a torn or bad frame."""
    head = stream.read(_HEADER.size)
    if not head:
        return None
    if len(head) < _HEADER.size:
        raise DeviceError(f"{peer}: stream ended inside a frame header")
    kind, size = _HEADER.unpack(head)
    want = _SIZES.get(kind)
    if kind not in _NAMES or (want is not None and size != want) or size > _MAX_JSON:
        raise DeviceError(f"{peer}: bad frame (type {kind}, {size} bytes)")
    body = stream.read(size) if size else b""
    if len(body) < size:
        raise DeviceError(f"{peer}: stream ended inside a {_NAMES[kind]} frame")
    return kind, body


def _json_body(body: bytes, peer: str) -> dict[str, Any]:
    try:
        obj = json.loads(body)
    except ValueError as exc:
        raise DeviceError(f"{peer}: handshake is not JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise DeviceError(f"{peer}: handshake is not a JSON object")
    return obj


class _Sender:
    """A socket's writing side: a thread sends what is queued, in order; `finish` sends BYE
    after what is queued and shuts the socket down (which ends the reader's stream too)."""

    def __init__(self, sock: socket.socket, name: str) -> None:
        self._sock = sock
        self._queue: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
        self.failed: OSError | None = None
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def send(self, data: bytes) -> None:
        self._queue.put(data)

    def finish(self, timeout_s: float = 2.0) -> None:
        self._queue.put(frame(BYE))
        self._queue.put(None)
        self._thread.join(timeout_s)

    def _run(self) -> None:
        while True:
            data = self._queue.get()
            if data is None:
                break
            if self.failed is not None:
                continue  # the peer is gone; its reader reports that
            try:
                self._sock.sendall(data)
            except OSError as exc:
                self.failed = exc
        with contextlib.suppress(OSError):  # already disconnected by the peer: nothing to shut
            self._sock.shutdown(socket.SHUT_RDWR)
        self._sock.close()


@dataclass(slots=True)
class _Follower:
    """The lead's view of one connected follower (guarded by the lead's lock)."""

    ident: int
    pid: int
    sock: socket.socket
    sender: _Sender
    sent: int = 0
    """Sequence number of the last EDGE or ADVANCE sent."""
    acked: int = 0
    idle: bool = False
    deadline: float = math.inf
    time_sent: float = -math.inf
    owed_since: float | None = None
    """Wall time (monotonic) since which the follower owes an acknowledgement, if it does."""

    def send_numbered(self, kind: int, record: struct.Struct, *fields: float) -> None:
        """Send an EDGE or ADVANCE: the follower owes its acknowledgement from now on."""
        self.sent += 1
        if self.owed_since is None:
            self.owed_since = time.monotonic()
        self.sender.send(frame(kind, record.pack(self.sent, *fields)))


class CableLead:
    """The lead world's end: listens, welcomes followers, copies its wire's edges to them and,
    on the virtual clock, is the `ClockLink` that makes their clocks one."""

    leads = True
    #: A lead is never spent: it accepts followers until closed.
    dead = False

    def __init__(self, world: SimWorld, params: CableParams) -> None:
        self.world, self.params, self.path = world, params, params.path
        self._label = f"trigger cable {self.path}"
        check_private_dir(self.path, create=True)
        self._listener = _bind(self.path, self._label)
        self._inode = os.stat(self.path).st_ino
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._followers: dict[int, _Follower] = {}
        self._next_ident = 1
        self._closing = False
        self._clock = world.clock if isinstance(world.clock, VirtualClock) else None
        if self._clock is not None:
            self._clock.attach(self)
        self._unsubscribe = world.wire.subscribe(self._on_edge)
        self._acceptor = threading.Thread(
            target=self._accept_loop, name=f"cable-lead-{world.name}", daemon=True
        )
        self._acceptor.start()
        self._watch_stop = threading.Event()
        if self._clock is not None and params.stall > 0:
            threading.Thread(target=self._watch, name=f"cable-lead-{world.name}-watch", daemon=True).start()
        log.info("%s: lead world %r listening (%s clock)", self._label, world.name, world.clock.mode)

    # -- state -------------------------------------------------------------------------
    @property
    def connected(self) -> int:
        with self._lock:
            return len(self._followers)

    def wait_followers(self, n: int, timeout_s: float) -> bool:
        """Wait (wall seconds) until at least `n` followers are connected."""
        with self._changed:
            return self._changed.wait_for(lambda: len(self._followers) >= n, timeout=timeout_s)

    def before_start(self) -> None:
        """The world's time must not start without its followers (they would miss the start)."""
        want = self.params.followers
        if not self.wait_followers(want, self.params.wait):
            raise DeviceError(
                f"{self._label}: {self.connected} of {want} follower(s) connected after "
                f"{self.params.wait:g} s (open the followers' devices, cable_role=follow, first)"
            )
        if self._clock is not None:
            # Ask every follower where it stands now: its devices may have started since its
            # last report, and the first advance must not pass a deadline it has not sent yet.
            self._clock.update(self._resync)

    def _resync(self) -> None:
        assert self._clock is not None
        now = self._clock.now_us()
        with self._lock:
            for f in self._followers.values():
                f.time_sent = now
                f.send_numbered(ADVANCE, _ADVANCE, now)

    def _change(self, fn: Callable[[], None]) -> None:
        """Apply a change to the follower table: under the clock's lock on the virtual clock
        (then let it advance), under ours on the real one."""
        if self._clock is not None:
            self._clock.update(fn)
        else:
            fn()

    # -- ClockLink (called with the clock's lock held) ---------------------------------
    def others_idle(self) -> bool:
        with self._lock:
            return all(f.idle and f.acked == f.sent for f in self._followers.values())

    def others_deadline(self) -> float:
        with self._lock:
            return min((f.deadline for f in self._followers.values()), default=math.inf)

    def advanced(self, now_us: float) -> None:
        with self._lock:
            for f in self._followers.values():
                if now_us > f.time_sent or f.deadline <= now_us:
                    f.time_sent = now_us
                    f.send_numbered(ADVANCE, _ADVANCE, now_us)

    def settled(self, idle: bool, deadline_us: float) -> None:
        raise AssertionError("the lead's clock does not report to anyone")

    # -- edges -------------------------------------------------------------------------
    def _on_edge(self, edge: Edge) -> None:
        """The box's thread, holding the world's time: queue the edge for every follower."""

        def send() -> None:
            with self._lock:
                for f in self._followers.values():
                    f.send_numbered(EDGE, _EDGE, 1 if edge.rising else 0, edge.true_us, edge.pulse_index)

        self._change(send)

    # -- connections -------------------------------------------------------------------
    def _accept_loop(self) -> None:
        while True:
            try:
                conn, _ = self._listener.accept()
            except OSError as exc:
                if not self._closing:
                    log.error("%s: accept failed, no more followers: %s", self._label, exc)
                return
            threading.Thread(
                target=self._serve, args=(conn,), name=f"cable-lead-{self.world.name}-rx", daemon=True
            ).start()

    def _serve(self, conn: socket.socket) -> None:
        stream = conn.makefile("rb")
        peer = f"{self._label}: follower"
        try:
            follower = self._welcome(conn, stream, peer)
        except (DeviceError, OSError) as exc:
            log.warning("%s refused: %s", peer, exc)
            stream.close()
            conn.close()
            return
        if follower is None:
            return
        peer = f"{self._label}: follower {follower.ident} (pid {follower.pid})"
        clean = False
        try:
            while (got := read_frame(stream, peer)) is not None:
                kind, body = got
                if kind == BYE:
                    clean = True
                    break
                if kind != STATE:
                    raise DeviceError(f"{peer}: unexpected {_NAMES[kind]} frame")
                state = _STATE.unpack(body)
                self._change(functools.partial(self._note_state, follower, *state))
        except (DeviceError, OSError, ValueError) as exc:
            if not self._closing:
                log.error("%s: %s", peer, exc)
        finally:
            stream.close()
            self._drop(follower, clean)

    def _welcome(self, conn: socket.socket, stream: IO[bytes], peer: str) -> _Follower | None:
        conn.settimeout(HANDSHAKE_S)
        got = read_frame(stream, peer)
        if got is None or got[0] != HELLO:
            raise DeviceError(f"{peer}: no HELLO")
        hello = _json_body(got[1], peer)
        world = self.world
        mine = {"version": VERSION, "world": world.name, "seed": world.seed, "clock": world.clock.mode}
        for key, value in mine.items():
            if hello.get(key) != value:
                why = f"the follower's {key} is {hello.get(key)!r}, the lead's {value!r}"
                conn.sendall(_json_frame(REFUSE, {"error": f"{self._label}: {why}"}))
                raise DeviceError(why)
        conn.settimeout(None)
        sender = _Sender(conn, f"cable-lead-{world.name}-tx")
        pid = int(hello.get("pid", 0))
        joined: list[_Follower] = []

        def join() -> None:
            with self._lock:
                if self._closing:
                    return
                follower = _Follower(self._next_ident, pid, conn, sender)
                self._next_ident += 1
                welcome: dict[str, Any] = {**mine, "epoch_ns": 0, "now_us": 0.0, "started": False}
                if self._clock is None:
                    welcome["epoch_ns"] = world.clock.epoch_ns  # type: ignore[union-attr]
                else:
                    # Virtual: the lead's host epoch, so the followers' host times agree with its own.
                    assert isinstance(world.host_clock, VirtualHostClock)
                    welcome["epoch_ns"] = world.host_clock.epoch_ns
                    welcome["now_us"] = self._clock.now_us()
                    welcome["started"] = self._clock.started
                    follower.time_sent = welcome["now_us"]
                sender.send(_json_frame(WELCOME, welcome))
                self._followers[follower.ident] = follower
                joined.append(follower)
                self._changed.notify_all()

        self._change(join)
        if not joined:
            sender.finish()
            return None
        log.info("%s: follower %d (pid %d) connected", self._label, joined[0].ident, pid)
        return joined[0]

    def _watch(self) -> None:
        """Drop a follower that has owed an acknowledgement for `cable_stall_s`: a stopped
        (not dead) process would otherwise stall the shared virtual time for good."""
        stall = self.params.stall
        while not self._watch_stop.wait(min(0.5, stall / 4)):
            now = time.monotonic()
            with self._lock:
                hung = [
                    f
                    for f in self._followers.values()
                    if f.owed_since is not None and now - f.owed_since > stall
                ]
            for f in hung:
                log.warning(
                    "%s: follower %d (pid %d) has not answered for %.1f s; dropping it so time goes on",
                    self._label,
                    f.ident,
                    f.pid,
                    stall,
                )
                with contextlib.suppress(OSError):  # its reader then sees the end and drops it
                    f.sock.shutdown(socket.SHUT_RDWR)

    def _note_state(self, f: _Follower, acked: int, idle: int, deadline: float) -> None:
        with self._lock:
            f.acked, f.idle, f.deadline = acked, bool(idle), deadline
            if acked == f.sent:
                f.owed_since = None

    def _drop(self, f: _Follower, clean: bool) -> None:
        def drop() -> None:
            with self._lock:
                self._followers.pop(f.ident, None)
                self._changed.notify_all()

        self._change(drop)
        f.sender.finish()
        if clean or self._closing:
            log.info("%s: follower %d (pid %d) disconnected", self._label, f.ident, f.pid)
        else:
            log.warning(
                "%s: follower %d (pid %d) hung up; time goes on without it", self._label, f.ident, f.pid
            )

    def close(self) -> None:
        """Stop listening, say goodbye to the followers (their worlds stop) and unlink the socket."""
        with self._lock:
            if self._closing:
                return
            self._closing = True
            followers = list(self._followers.values())
        self._watch_stop.set()
        self._unsubscribe()
        with contextlib.suppress(OSError):  # wakes accept(); close() ends it where shutdown is refused
            self._listener.shutdown(socket.SHUT_RDWR)
        self._listener.close()
        self._acceptor.join(2.0)
        for f in followers:
            f.sender.finish()
        try:
            if os.stat(self.path).st_ino == self._inode:
                os.unlink(self.path)
        except FileNotFoundError:
            pass  # someone removed it already: nothing to clean
        log.info("%s: lead closed", self._label)


def _bind(path: str, label: str) -> socket.socket:
    """Listen on `path`, replacing a stale socket a dead lead left; refuse a live one or a file."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        st = None
    if st is not None:
        if not stat.S_ISSOCK(st.st_mode):
            raise ConfigError(f"{label}: {path} exists and is not a socket")
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            probe.connect(path)
        except OSError:
            os.unlink(path)  # nobody listens: a lead that died left it
        else:
            raise DeviceError(f"{label}: another lead world already listens there")
        finally:
            probe.close()
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.bind(path)
        os.chmod(path, 0o600)
        sock.listen(16)
    except OSError as exc:
        sock.close()
        raise DeviceError(f"{label}: cannot listen: {exc}") from exc
    return sock


class CableFollower:
    """A follower world's end: connects (waiting, bounded, for the lead to listen), adopts the
    lead's time, fires the lead's edges on its own wire and, on the virtual clock, is the
    `ClockLink` through which its clock follows the lead's."""

    leads = False

    def __init__(self, world: SimWorld, params: CableParams) -> None:
        self.world, self.params, self.path = world, params, params.path
        self._label = f"trigger cable {self.path}"
        self.dead = False
        self.edges = 0
        self._acked = 0
        self._reported: tuple[int, bool, float] | None = None
        self._closing = False
        sock = _connect(self.path, self._label, params.wait)
        self._stream = sock.makefile("rb")
        try:
            welcome = self._handshake(sock)
        except BaseException:
            self._stream.close()
            sock.close()
            raise
        self._sender = _Sender(sock, f"cable-follow-{world.name}-tx")
        self._clock = world.clock if isinstance(world.clock, VirtualClock) else None
        if self._clock is None:
            world.clock.adopt_epoch(int(welcome["epoch_ns"]))  # type: ignore[union-attr]
        else:
            assert isinstance(world.host_clock, VirtualHostClock)
            world.host_clock.adopt_epoch(int(welcome["epoch_ns"]))
            self._clock.update(to_us=float(welcome["now_us"]))
            self._clock.attach(self)  # reports its first STATE
        self._reader = threading.Thread(
            target=self._read_loop, name=f"cable-follow-{world.name}", daemon=True
        )
        self._reader.start()
        log.info("%s: world %r follows its lead (%s clock)", self._label, world.name, world.clock.mode)

    def _handshake(self, sock: socket.socket) -> dict[str, Any]:
        world = self.world
        hello = {"version": VERSION, "world": world.name, "seed": world.seed, "clock": world.clock.mode}
        sock.settimeout(HANDSHAKE_S)
        try:
            sock.sendall(_json_frame(HELLO, {**hello, "pid": os.getpid()}))
            got = read_frame(self._stream, self._label)
        except OSError as exc:
            raise DeviceError(f"{self._label}: handshake with the lead failed: {exc}") from exc
        sock.settimeout(None)
        if got is None:
            raise DeviceError(f"{self._label}: the lead hung up during the handshake")
        kind, body = got
        answer = _json_body(body, self._label)
        if kind == REFUSE:
            raise ConfigError(str(answer.get("error", f"{self._label}: refused by the lead")))
        if kind != WELCOME or any(answer.get(k) != v for k, v in hello.items()):
            raise DeviceError(f"{self._label}: the lead answered {_NAMES.get(kind)} {answer!r}")
        return answer

    # -- ClockLink (called with the clock's lock held) ---------------------------------
    def others_idle(self) -> bool:
        return True

    def others_deadline(self) -> float:
        return math.inf

    def advanced(self, now_us: float) -> None:
        raise AssertionError("a follower's clock is moved by its lead")

    def before_start(self) -> None:
        pass  # a follower's time is its lead's

    def settled(self, idle: bool, deadline_us: float) -> None:
        state = (self._acked, idle, deadline_us)
        if self.dead or state == self._reported:
            return
        self._reported = state
        self._sender.send(frame(STATE, _STATE.pack(self._acked, 1 if idle else 0, deadline_us)))

    def _ack(self, seq: int) -> None:
        self._acked = seq

    # -- the lead's stream -------------------------------------------------------------
    def _read_loop(self) -> None:
        why = "the lead hung up"
        clean = False
        try:
            while (got := read_frame(self._stream, self._label)) is not None:
                kind, body = got
                if kind == EDGE:
                    seq, rising, true_us, index = _EDGE.unpack(body)
                    self.world.wire.fire(Edge(rising=bool(rising), true_us=true_us, pulse_index=index))
                    self.edges += 1
                    if self._clock is not None:
                        self._clock.update(functools.partial(self._ack, seq))
                elif kind == ADVANCE and self._clock is not None:
                    seq, now_us = _ADVANCE.unpack(body)
                    self._clock.update(functools.partial(self._ack, seq), to_us=now_us)
                elif kind == BYE:
                    why, clean = "the lead closed the cable", True
                    break
                else:
                    raise DeviceError(f"{self._label}: unexpected {_NAMES[kind]} frame from the lead")
        except (DeviceError, OSError, ValueError) as exc:
            why = str(exc)
        finally:
            self.dead = True
            self._stream.close()
            self._sender.finish()
        if self._closing:
            return
        level = logging.INFO if clean else logging.ERROR
        world = self.world.name
        log.log(level, "%s: %s; world %r stops here (its devices can be closed)", self._label, why, world)

    def close(self) -> None:
        """Hang up (the lead drops this follower and goes on)."""
        if self._closing:
            return
        self._closing = True
        self._sender.finish()
        self._reader.join(2.0)


def _connect(path: str, label: str, wait_s: float) -> socket.socket:
    """Connect, trying again while the lead is not listening yet, for at most `wait_s`."""
    deadline = time.monotonic() + wait_s
    parent = os.path.dirname(path)
    while True:
        if os.path.isdir(parent):
            check_private_dir(path, create=False)  # an insecure directory: refused at once
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                sock.connect(path)
                return sock
            except OSError as exc:
                sock.close()
                if exc.errno not in (errno.ENOENT, errno.ECONNREFUSED):
                    raise DeviceError(f"{label}: cannot connect: {exc}") from exc
                last = "nothing listens there" if exc.errno == errno.ECONNREFUSED else "no socket there"
        else:
            last = "its directory is not there"
        if time.monotonic() >= deadline:
            raise DeviceError(
                f"{label}: no lead world after {wait_s:g} s ({last}); start the lead's devices "
                "(cable_role=lead) or raise cable_wait_s"
            )
        time.sleep(_RETRY_S)
