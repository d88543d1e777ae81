"""The writer thread's accounting when the file system refuses a write: data the take already
holds (it writes it when it is failed) is the take's, never also recorded as lost; data the
take does not hold is recorded as lost, once."""

from __future__ import annotations

import errno
from types import SimpleNamespace
from typing import Any

import pytest

from rigd.app.capture.control import RunControl
from rigd.app.capture.faults import FaultBoard
from rigd.app.capture.writer_loop import WriterLoop
from rigd.core.errors import WriteDeferredError


class _Stream:
    """A device stream whose every write the file system refuses with `error`."""

    def __init__(self, error: OSError) -> None:
        self.error = error
        self.live = SimpleNamespace(dequeued=lambda: None)
        self.landed_items: list[Any] = []

    def write(self, writer: object, item: object) -> None:
        raise self.error

    def landed(self, item: object) -> None:
        self.landed_items.append(item)


class _Ledger:
    def __init__(self) -> None:
        self.lost: list[tuple[str, str, int, str]] = []

    def add(self, device: str, what: str, count: int, reason: str) -> None:
        self.lost.append((device, what, count, reason))


def _loop(error: OSError) -> tuple[WriterLoop, _Stream, _Ledger, FaultBoard, RunControl]:
    stream, ledger, faults, control = _Stream(error), _Ledger(), FaultBoard(), RunControl()
    writer = SimpleNamespace(path=SimpleNamespace(name="t.h5"))
    loop = WriterLoop(writer, None, {"ev0": stream}, ledger, faults, control, None, 1.0)  # type: ignore[arg-type,dict-item]
    return loop, stream, ledger, faults, control


@pytest.mark.parametrize(
    ("error", "kept"),
    [
        (WriteDeferredError(errno.ENOSPC, "No space left on device"), True),
        (OSError(errno.ENOSPC, "No space left on device"), False),
    ],
)
def test_a_refused_write_counts_the_item_once(error: OSError, kept: bool) -> None:
    loop, stream, ledger, faults, control = _loop(error)
    item = SimpleNamespace(device="ev0", what="events", count=1234)
    loop._take(item)  # type: ignore[arg-type]
    assert loop.error is error
    assert control.stop_requested.is_set()
    assert [f.code for f in faults.active()] == ["disk_full"]
    if kept:
        assert stream.landed_items == [item]
        assert ledger.lost == []
    else:
        assert stream.landed_items == []
        assert [lost[:3] for lost in ledger.lost] == [("ev0", "events", 1234)]
    # what comes after the failed write is not written, and is recorded as lost
    loop._take(SimpleNamespace(device="ev0", what="events", count=7))  # type: ignore[arg-type]
    assert ledger.lost[-1][:3] == ("ev0", "events", 7)
    assert "the take stopped" in ledger.lost[-1][3]
