"""What the EVT codec tests share: the real recordings, chunked feeding and array comparison."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, settings

from drivers.evt import Decoded, StreamDecoder, parse_raw_header
from rigd.core.events import EventArray, TriggerEvents

DATA = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "events"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"real Prophesee recordings not found at {DATA}")
SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def real_body(name: str) -> bytes:
    """The event stream of a real RAW recording, its header skipped."""
    with (DATA / name).open("rb") as f:
        parse_raw_header(f)
        return f.read()


def feed_chunks(dec: StreamDecoder, data: bytes, sizes: list[int]) -> Iterator[Decoded]:
    """`dec.feed` over data cut into pieces of `sizes` (cycled), then `dec.finish()` (what words
    held back at the end decode to); what came before a strict-mode error has been yielded when
    it raises."""
    pos = i = 0
    while pos < len(data):
        k = sizes[i % len(sizes)]
        yield dec.feed(memoryview(data)[pos : pos + k])
        pos += k
        i += 1
    yield dec.finish()


def assert_same(a: EventArray | TriggerEvents, b: EventArray | TriggerEvents) -> None:
    assert len(a) == len(b)
    for name in a.__slots__:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def assert_matches_pypi_evt3(events: EventArray, name: str) -> None:
    """`events` are what the evt3 PyPI package decodes from the real recording `name`."""
    evt3_pkg = pytest.importorskip("evt3", reason="evt3 PyPI package not installed")
    ref = evt3_pkg.decode_file(str(DATA / name))
    np.testing.assert_array_equal(events.x, ref.x)
    np.testing.assert_array_equal(events.y, ref.y)
    np.testing.assert_array_equal(events.p, ref.polarity.astype(np.int8) * 2 - 1)
    np.testing.assert_array_equal(events.t, ref.timestamp.astype(np.int64))
