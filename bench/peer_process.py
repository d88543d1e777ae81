"""A peer's code in its own process and venv, answering timed requests one JSON line at a time.

The benches that put a peer beside rigd (v2e, evt3, expelliarmus) run it in a worker script
under the peer's own python, so the two never share imports, threads or allocators. The worker
prints one JSON line when it is ready (what it runs), then answers each request line with
`{"seconds": ..., "events": ...}`.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path
from typing import Any


class PeerProcess:
    """One worker process: `hello` is its first line; `run` sends a request and times nothing
    itself (the worker measures its own call)."""

    def __init__(self, argv: list[str], *, cpu: int | None = None, close_timeout_s: float = 60.0) -> None:
        self.proc = subprocess.Popen(
            argv,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            preexec_fn=(lambda: os.sched_setaffinity(0, {cpu})) if cpu is not None else None,
        )
        self._close_timeout_s = close_timeout_s
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(
                f"peer worker {Path(argv[1]).name} ({argv[0]}) did not start: is the peer on its path?"
            )
        self.hello: dict[str, Any] = json.loads(line)

    def run(self, request: str) -> tuple[float, int]:
        """(seconds, events) of one request, as the worker measured them."""
        answer = self.ask(request)
        return float(answer["seconds"]), int(answer["events"])

    def ask(self, request: str) -> dict[str, Any]:
        """The worker's whole answer to one request (what it measured beyond seconds/events)."""
        assert self.proc.stdin is not None
        assert self.proc.stdout is not None
        self.proc.stdin.write(request + "\n")
        self.proc.stdin.flush()
        answer: dict[str, Any] = json.loads(self.proc.stdout.readline())
        return answer

    def close(self) -> None:
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        self.proc.wait(timeout=self._close_timeout_s)
