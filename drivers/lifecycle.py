"""What every acquiring device shares: an acquisition thread, the bounded queue it fills and
the slot that keeps the error that ended it.

Backends write no threads, condition variables or error slots of their own. The device base
classes (`drivers.base`) run the backend's `_grab(timeout_s)` on an `Acquisition`; what it
returns waits in a `DeliveryQueue` whose overflow is counted, and an exception that ends the
thread is kept and raised by the next read, so an unplugged device is reported where the
caller reads.
"""

from __future__ import annotations

import collections
import enum
import logging
import threading
from collections.abc import Callable
from typing import Generic, Literal, TypeVar

from rigd.core.errors import DeviceError

log = logging.getLogger(__name__)

T = TypeVar("T")

#: Which item a full queue gives up: the one arriving (a camera's on-board buffer) or the
#: oldest waiting (a live view that must stay current).
Drop = Literal["newest", "oldest"]


class Signal(enum.Enum):
    """What `_grab` may return besides an item or None (nothing within the timeout)."""

    END = "end"
    """The device has nothing more to give (end of a recording, a stopped stream drained)."""


END = Signal.END


class DeliveryQueue(Generic[T]):
    """Bounded hand-over from an acquisition thread to the readers; overflow is counted."""

    def __init__(self, maxlen: int, drop: Drop = "newest") -> None:
        if maxlen < 1:
            raise ValueError(f"queue length must be >= 1, got {maxlen}")
        self.maxlen = maxlen
        self.drop = drop
        self._items: collections.deque[T] = collections.deque()
        self._cond = threading.Condition()
        self._dropped = 0

    @property
    def dropped(self) -> int:
        """Items given up because the queue was full."""
        with self._cond:
            return self._dropped

    def put(self, item: T) -> T | None:
        """Queue an item; returns the one given up when the queue was full, else None."""
        with self._cond:
            lost: T | None = None
            if len(self._items) >= self.maxlen:
                self._dropped += 1
                if self.drop == "newest":
                    return item
                lost = self._items.popleft()
            self._items.append(item)
            self._cond.notify_all()
            return lost

    def get(
        self, timeout_s: float, *, max_items: int | None = 1, until: Callable[[], bool] | None = None
    ) -> list[T]:
        """Up to `max_items` (None: all) queued items, waiting at most `timeout_s` for the first;
        returns early, empty, once `until()` holds (the producer ended or failed)."""
        with self._cond:
            if not self._items and timeout_s > 0:
                self._cond.wait_for(
                    lambda: bool(self._items) or (until is not None and until()), timeout=timeout_s
                )
            n = len(self._items) if max_items is None else min(max_items, len(self._items))
            taken = [self._items.popleft() for _ in range(n)]
            if taken:
                self._cond.notify_all()  # a producer may be waiting for room (`wait_room`)
            return taken

    def wait_room(self, timeout_s: float, below: int | None = None) -> bool:
        """Wait at most `timeout_s` until fewer than `below` (default: the length) items are
        queued; a producer that must not lose data (a simulated device on virtual time) waits
        here instead of dropping, and may keep itself closer to its reader than a full queue."""
        limit = self.maxlen if below is None else max(1, min(below, self.maxlen))
        with self._cond:
            return self._cond.wait_for(lambda: len(self._items) < limit, timeout=timeout_s)

    def drain(self) -> list[T]:
        """Every queued item, oldest first (what an unplug takes with it)."""
        return self.get(0.0, max_items=None)

    def wake(self) -> None:
        """Wake the readers so they look at the producer's state again."""
        with self._cond:
            self._cond.notify_all()

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)


Grab = Callable[[float], T | Signal | None]


class Acquisition(Generic[T]):
    """One acquisition thread: calls `grab(poll_s)` until stopped and delivers what it returns.

    `grab` returns an item, None (nothing within the timeout) or END. After `stop()` the thread
    ends at once, or with `drain_on_stop` once `grab` has nothing more (exposures already
    triggered still complete). An exception from `grab` ends the thread; it is logged and kept,
    and `read` raises it as DeviceError once the queue is empty, so data grabbed before the
    failure stays readable.
    """

    def __init__(
        self,
        label: str,
        grab: Grab[T],
        queue: DeliveryQueue[T],
        *,
        deliver: Callable[[T], object] | None = None,
        drain_on_stop: bool = False,
        poll_s: float = 0.05,
        join_timeout_s: float | None = None,
    ) -> None:
        self.label = label
        self.queue = queue
        self.stopping = threading.Event()
        self._grab = grab
        self._deliver: Callable[[T], object] = deliver if deliver is not None else queue.put
        self._drain_on_stop = drain_on_stop
        self._poll_s = poll_s
        self._join_timeout_s = join_timeout_s
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._ended = False

    @property
    def error(self) -> BaseException | None:
        """The error that ended the thread (or that `fail` recorded), until the next start."""
        return self._error

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        """Start a fresh thread; a previous run's error is forgotten."""
        if self.alive:
            raise DeviceError(f"{self.label}: acquisition is already running")
        self._error = None
        self._ended = False
        self.stopping.clear()
        self._thread = threading.Thread(target=self._run, name=f"acq-{self.label}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Ask the thread to end and wait for it (a no-op when it is not running)."""
        self.stopping.set()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(self._join_timeout_s)
            if thread.is_alive():
                log.warning("%s: acquisition thread still busy after %s s", self.label, self._join_timeout_s)
        self.queue.wake()

    def fail(self, exc: BaseException) -> None:
        """Keep an error found beside `grab` (first one wins) and wake the readers."""
        if self._error is None:
            self._error = exc
        self.queue.wake()

    def read(self, timeout_s: float, *, max_items: int | None = 1) -> list[T]:
        """Queued items first; then the kept error as DeviceError; else wait up to `timeout_s`."""
        items = self.queue.get(timeout_s, max_items=max_items, until=self._idle)
        if not items and self._error is not None:
            raise kept_error(self.label, self._error)
        return items

    def _idle(self) -> bool:
        return self._error is not None or self._ended or not self.alive

    def _run(self) -> None:
        try:
            while not (self.stopping.is_set() and not self._drain_on_stop):
                item = self._grab(self._poll_s)
                if item is END:
                    break
                if item is None:
                    if self.stopping.is_set():
                        break
                    continue
                self._deliver(item)
        except Exception as exc:  # kept for the readers: `read` raises it as DeviceError
            log.exception("%s: acquisition failed", self.label)
            self.fail(exc)
        finally:
            self._ended = True  # before the wake: a waiting reader sees the end at once
            self.queue.wake()


def kept_error(label: str, exc: BaseException) -> DeviceError:
    """The DeviceError a reader gets for an error kept from the acquisition thread."""
    if isinstance(exc, DeviceError):
        err = DeviceError(str(exc))
    else:
        err = DeviceError(f"{label}: acquisition failed: {exc!r}")
    err.__cause__ = exc
    return err
