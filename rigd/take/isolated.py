"""Reading a take in a worker process with a deadline, so a hang or crash costs only that take.

The structural check (rigd/take/structure.py) refuses everything known to make HDF5 read outside
a take; this is the bound on what is not known: a take whose read blocks (a file system that
hangs, a FIFO a future HDF5 feature reaches), loops, or kills its reader (a crash in a filter
plugin). The daemon's console and control threads, its start-up recovery, and `rigd takes` /
`rigd recover DIR` read each take through `run_isolated`: the worker is killed at the deadline
and the caller reports the take as unreadable, never waiting on it.

Workers come from a forkserver (a fork of a clean process that imported the reader once), not
from a fork of the caller: the daemon has threads, and a fork holds whatever locks they held.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import multiprocessing.connection
from collections.abc import Callable
from typing import Any, TypeVar

from rigd.core.errors import RigdError, TakeError, TakeFormatError, TakeInUseError

log = logging.getLogger(__name__)

T = TypeVar("T")

#: Deadline of one take's summary or preview (a multi-hour take summarizes in well under 1 s).
READ_TIMEOUT_S = 30.0

#: Modules the forkserver imports once, so each worker starts without importing them again.
_PRELOAD = ["rigd.take.reader", "rigd.take.recover"]
_ctx: Any = None


class TakeReadTimeoutError(TakeError):
    """Reading a take did not finish by its deadline; the worker reading it was killed."""


class TakeReaderCrashedError(TakeError):
    """The worker reading a take died without an answer (a crash in HDF5 or a filter)."""


def _context() -> Any:
    global _ctx
    if _ctx is None:
        ctx = mp.get_context("forkserver")
        ctx.set_forkserver_preload(_PRELOAD)
        _ctx = ctx
    return _ctx


def _child(
    conn: multiprocessing.connection.Connection, fn: Callable[..., Any], args: tuple[Any, ...]
) -> None:
    try:
        result = fn(*args)
    except BaseException as exc:  # noqa: BLE001 - sent to the caller, which raises it again
        kind = (
            "in_use"
            if isinstance(exc, TakeInUseError)
            else "format"
            if isinstance(exc, TakeFormatError)
            else "take"
            if isinstance(exc, TakeError)
            else "rigd"
            if isinstance(exc, RigdError)
            else "os"
            if isinstance(exc, OSError)
            else "other"
        )
        conn.send(("error", kind, str(exc) or type(exc).__name__, type(exc).__name__))
    else:
        conn.send(("ok", result))
    conn.close()


def _raise(kind: str, message: str, type_name: str) -> None:
    if kind == "in_use":
        raise TakeInUseError(message)
    if kind == "format":
        raise TakeFormatError(message)
    if kind == "take":
        raise TakeError(message)
    if kind == "rigd":
        raise RigdError(message)
    if kind == "os":
        raise OSError(message)
    raise RuntimeError(f"{type_name}: {message}")


def run_isolated(fn: Callable[..., T], *args: Any, timeout_s: float, what: str) -> T:
    """`fn(*args)` in a worker process, its result (picklable) or its error raised here again
    (RigdError classes keep their class, others become RuntimeError); TakeReadTimeoutError
    when it did not answer within `timeout_s`, TakeReaderCrashedError when it died. `what`
    names the take in those errors."""
    ctx = _context()
    parent, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(child, fn, args), name=f"rigd read {what}", daemon=True)
    proc.start()
    child.close()
    try:
        if not parent.poll(timeout_s):
            log.error("reading %s did not finish within %g s: its reader is killed", what, timeout_s)
            raise TakeReadTimeoutError(
                f"{what}: reading it did not finish within {timeout_s:g} s (a file it points at "
                "blocks, or a damaged structure loops); not read"
            )
        try:
            answer = parent.recv()
        except EOFError:
            proc.join(5)
            raise TakeReaderCrashedError(
                f"{what}: its reader died without an answer (exit code {proc.exitcode}); not read"
            ) from None
    finally:
        parent.close()
        if proc.is_alive():
            proc.kill()
        proc.join()
    if answer[0] == "ok":
        return answer[1]
    _raise(*answer[1:])
    raise AssertionError("unreachable")


def recovery_timeout_s(size_bytes: int) -> float:
    """Deadline of sealing one take: finalize rewrites every event time, ~1 min per 10 GB on a
    slow disk; twice that and a floor, so only a take that hangs runs into it."""
    return 120.0 + 12.0 * size_bytes / 1e9
