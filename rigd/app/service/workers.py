"""The bounded pool of control-loop workers for slow commands."""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable

log = logging.getLogger(__name__)


class WorkerPool:
    """A fixed number of threads working off a bounded queue: `submit` says at once whether
    the job was taken, so the control loop can answer `busy` instead of piling up threads."""

    def __init__(self, workers: int, depth: int, name: str) -> None:
        self._queue: queue.Queue[Callable[[], None] | None] = queue.Queue(maxsize=depth)
        self._threads = [
            threading.Thread(target=self._run, name=f"{name}-{i}", daemon=True) for i in range(workers)
        ]
        self.failures = 0

    def start(self) -> None:
        for t in self._threads:
            t.start()

    def submit(self, job: Callable[[], None]) -> bool:
        """Queue `job`; False when the queue is full."""
        try:
            self._queue.put_nowait(job)
        except queue.Full:
            return False
        return True

    def _run(self) -> None:
        while (job := self._queue.get()) is not None:
            try:
                job()
            except Exception:  # a failed job must not shrink the pool; logged with its traceback
                self.failures += 1
                log.exception("control worker job failed")

    def close(self, timeout_s: float) -> None:
        """Let queued jobs finish (up to `timeout_s` in all), then end the threads."""
        deadline = time.monotonic() + timeout_s
        for _ in self._threads:
            try:
                self._queue.put(None, timeout=max(0.0, deadline - time.monotonic()))
            except queue.Full:
                log.warning("control workers still busy after %.0f s; not waiting for them", timeout_s)
                return
        for t in self._threads:
            if t.is_alive():
                t.join(timeout=max(0.0, deadline - time.monotonic()))
