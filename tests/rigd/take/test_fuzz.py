"""Fuzzing real takes: hypothesis mutates a take the writer made (attributes, dtypes, shapes,
index rows, links, external storage, truncation, overwritten bytes) and every read a consumer
makes must end in a correct read or a TakeError, within a deadline and a memory bound.

Each read runs in a worker process (rigd.take.isolated) with a deadline, so a hang is a failure
here rather than a stuck suite, and reports the peak of what it allocated (tracemalloc: numpy's
arrays included). A fast budget runs in the normal suite; the long one is marked slow.
"""

from __future__ import annotations

import re
import shutil
import tempfile
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware_sim.testing.takes import make_take
from rigd.app.testing.crash import append_words_step, open_words_writer, unfinished
from rigd.core.errors import TakeError
from rigd.take.isolated import run_isolated
from tests.rigd.take.test_hostile import read_everything

#: What one read may allocate (tracemalloc peak) in a take of a few MB, whatever it declares.
MEMORY_BOUND = 256 << 20
#: Deadline of one read in its worker: a hang, not a slow machine, runs into it.
DEADLINE_S = 120.0

_BASES: dict[str, Path] = {}


def _base(kind: str) -> Path:
    """The real take each example starts from (made once per session)."""
    if kind not in _BASES:
        d = Path(tempfile.mkdtemp(prefix="rigd-fuzz-"))
        if kind == "complete":
            _BASES[kind] = make_take(d / "complete.h5").path
        elif kind == "unfinished":
            _BASES[kind] = unfinished(d / "unfinished.h5", n=6)
        else:
            from rigd.evt import StreamDecoder

            w = open_words_writer(d / "words.h5")
            dec = StreamDecoder("evt3")
            for k in range(6):
                append_words_step(w, dec, k)
            w.flush()
            w.close()
            _BASES[kind] = d / "words.h5"
    return _BASES[kind]


def _objects(f: h5py.File) -> list[str]:
    out: list[str] = []
    f.visit(out.append)
    return sorted(out)


def _datasets(f: h5py.File) -> list[str]:
    return [n for n in _objects(f) if isinstance(f[n], h5py.Dataset)]


# -- mutations: (file, draw) -> None; `draw` picks from what the file holds --------------------
Draw = Callable[[Any], Any]

VALUES = st.one_of(
    st.integers(-(2**63), 2**63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20),
    st.sampled_from(["wide", "evt9", "rgb99", "[" * 2000, '{"a": 1', "", "complete", "rig", "1.99"]),
    st.lists(st.integers(-5, 5), max_size=4).map(lambda v: np.asarray(v, np.int64)),
)
DTYPES = st.sampled_from(["int8", "uint8", "uint16", "int32", "int64", "uint64", "float32", "float64"])


def _set_attr(f: h5py.File, draw: Draw) -> None:
    obj = f[draw(st.sampled_from(["/", *_objects(f)]))]
    keys = sorted(obj.attrs)
    key = (
        draw(st.sampled_from(keys)) if keys and draw(st.booleans()) else draw(st.text(min_size=1, max_size=8))
    )
    obj.attrs[key] = draw(VALUES)


def _del_attr(f: h5py.File, draw: Draw) -> None:
    obj = f[draw(st.sampled_from(["/", *_objects(f)]))]
    if obj.attrs:
        del obj.attrs[draw(st.sampled_from(sorted(obj.attrs)))]


def _retype(f: h5py.File, draw: Draw) -> None:
    name = draw(st.sampled_from(_datasets(f)))
    ds = f[name]
    # A dataset an earlier mutation resized to a huge length is retyped as a stub: reading it
    # whole would ask this test for terabytes.
    data = ds[()] if ds.size <= 1 << 20 else np.zeros(3, ds.dtype)
    del f[name]
    dt = draw(DTYPES)
    f[name] = (
        np.asarray(data).astype(dt)
        if getattr(data, "dtype", np.dtype("O")).kind in "iufb"
        else np.zeros(3, dt)
    )


def _reshape(f: h5py.File, draw: Draw) -> None:
    name = draw(st.sampled_from(_datasets(f)))
    del f[name]
    shape = tuple(draw(st.lists(st.integers(0, 9), min_size=0, max_size=3)))
    f[name] = np.zeros(shape, draw(DTYPES))


def _resize(f: h5py.File, draw: Draw) -> None:
    chunked = [n for n in _datasets(f) if f[n].chunks is not None and f[n].maxshape[0] is None]
    if chunked:
        ds = f[draw(st.sampled_from(chunked))]
        ds.resize((draw(st.sampled_from([0, 1, ds.shape[0] + 1, 10**6, 10**9, 2**40])), *ds.shape[1:]))


def _index_rows(f: h5py.File, draw: Draw) -> None:
    names = [
        n for n in _datasets(f) if n.split("/")[-1] in ("ms_to_idx", "evt_index", "pulse_index", "index")
    ]
    if names:
        ds = f[draw(st.sampled_from(names))]
        if ds.size:
            flat = np.unravel_index(draw(st.integers(0, ds.size - 1)), ds.shape)
            ds[flat] = draw(st.sampled_from([0, -1, 1, 2**31, 2**62, -(2**62)]))


def _delete(f: h5py.File, draw: Draw) -> None:
    del f[draw(st.sampled_from(_objects(f)))]


def _link(f: h5py.File, draw: Draw) -> None:
    target = draw(st.sampled_from(["/", "/etc/passwd", *_objects(f)]))
    kind = draw(st.sampled_from(["soft", "external", "loop"]))
    where = draw(st.sampled_from(["events", "frames", "trigger", "sync", "calibration"]))
    g = f.require_group(where)
    if kind == "soft":
        g["x"] = h5py.SoftLink(target)
    elif kind == "external":
        g["x"] = h5py.ExternalLink("/etc/passwd", "/")
    else:
        g["a"] = h5py.SoftLink(f"/{where}/b")
        g["b"] = h5py.SoftLink(f"/{where}/a")


def _external(f: h5py.File, draw: Draw) -> None:
    name = draw(st.sampled_from(_datasets(f)))
    ds = f[name]
    shape, dtype = ds.shape, ds.dtype if ds.dtype.kind in "iufb" else np.dtype("uint8")
    del f[name]
    n = max(1, int(np.prod(shape))) * dtype.itemsize
    f.create_dataset(name, shape or (1,), dtype, external=[("/dev/zero", 0, n)])


def _virtual(f: h5py.File, draw: Draw) -> None:
    name = draw(st.sampled_from(_datasets(f)))
    n = max(1, f[name].shape[0] if f[name].ndim else 1)
    layout = h5py.VirtualLayout(shape=(n,), dtype=np.int64)
    layout[:] = h5py.VirtualSource("/etc/passwd", "data", shape=(n,))
    del f[name]
    f.create_virtual_dataset(name, layout)


MUTATIONS = [
    _set_attr,
    _del_attr,
    _retype,
    _reshape,
    _resize,
    _index_rows,
    _delete,
    _link,
    _external,
    _virtual,
]


def _read_measured(path: Path) -> tuple[str, int]:
    """In the worker: every consumer's read; ('ok' or the error's class and text, peak bytes)."""
    tracemalloc.start()
    try:
        read_everything(path)
        outcome = "ok"
    except TakeError as exc:
        outcome = f"TakeError {type(exc).__name__}: {exc}"
    except BaseException as exc:  # noqa: BLE001 - what the test reports as the failure
        outcome = f"UNCLEAN {type(exc).__name__}: {exc}"
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return outcome, peak


def _fuzz_one(tmp: Path, data: st.DataObject) -> None:
    kind = data.draw(st.sampled_from(["complete", "unfinished", "words"]), label="take")
    p = tmp / "fuzz.h5"
    shutil.copy(_base(kind), p)
    done = []
    with h5py.File(p, "r+") as f:
        for _ in range(data.draw(st.integers(1, 3), label="mutations")):
            mutate = data.draw(st.sampled_from(MUTATIONS), label="mutation")
            try:
                mutate(f, data.draw)
            except (OSError, ValueError, TypeError, OverflowError, KeyError, RuntimeError):
                continue  # h5py refused this edit (an earlier one broke what it reads): not applied
            done.append(mutate.__name__)
    cut = data.draw(st.one_of(st.none(), st.floats(0.0, 1.0)), label="truncate at")
    if cut is not None:
        size = p.stat().st_size
        with p.open("r+b") as fh:
            fh.truncate(int(size * cut))
    noise = data.draw(
        st.one_of(st.none(), st.tuples(st.floats(0.0, 1.0), st.binary(min_size=1, max_size=64)))
    )
    if noise is not None and p.stat().st_size:
        with p.open("r+b") as fh:
            fh.seek(int(p.stat().st_size * noise[0]))
            fh.write(noise[1])
    outcome, peak = run_isolated(_read_measured, p, timeout_s=DEADLINE_S, what=f"{kind} take after {done}")
    assert not outcome.startswith("UNCLEAN"), (kind, done, cut, outcome)
    assert peak < MEMORY_BOUND, (kind, done, cut, peak)


_COMMON = {
    "deadline": None,
    "derandomize": False,
    "suppress_health_check": [HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
}


@settings(max_examples=6, **_COMMON)  # type: ignore[arg-type]
@given(data=st.data())
def test_mutated_takes_read_cleanly(tmp_path: Path, data: st.DataObject) -> None:
    _fuzz_one(tmp_path, data)


@pytest.mark.slow
@pytest.mark.timeout(1800)  # the long budget: minutes, beyond the suite's 300 s per test
@settings(max_examples=400, **_COMMON)  # type: ignore[arg-type]
@given(data=st.data())
def test_mutated_takes_read_cleanly_long(tmp_path: Path, data: st.DataObject) -> None:
    _fuzz_one(tmp_path, data)


def _words_fmt(f: h5py.File) -> None:
    f["events/ev0"].attrs["evt_format"] = "evt9"


def _words_index_1d(f: h5py.File) -> None:
    d = f["events/ev0/evt_index"][...]
    del f["events/ev0/evt_index"]
    f["events/ev0/evt_index"] = d.reshape(-1)


def _words_index_3_columns(f: h5py.File) -> None:
    d = f["events/ev0/evt_index"][...]
    del f["events/ev0/evt_index"]
    f["events/ev0/evt_index"] = d[:, :3]


def _words_as_text(f: h5py.File) -> None:
    del f["events/ev0/evt_words"]
    f["events/ev0/evt_words"] = "words"


def _words_count_overflow(f: h5py.File) -> None:
    f["events/ev0/evt_index"][0, 2] = 2**62


@pytest.mark.parametrize(
    "edit",
    [_words_fmt, _words_index_1d, _words_index_3_columns, _words_as_text, _words_count_overflow],
    ids=lambda e: e.__name__,
)
def test_damaged_evt_words_metadata_is_one_take_error(
    tmp_path: Path, edit: Callable[[h5py.File], None]
) -> None:
    """The evt_words variants of the issue's list (an unknown format, a 1-D or 3-column index,
    text for words, an event count that overflows): one TakeFormatError naming the file."""
    p = tmp_path / "words.h5"
    shutil.copy(_base("words"), p)
    with h5py.File(p, "r+") as f:
        edit(f)
    outcome, _ = _read_measured(p)
    assert outcome.startswith("TakeError TakeFormatError"), outcome
    assert str(p) in outcome


@pytest.mark.parametrize(
    ("column", "value", "match"),
    [
        (1, 2**31, "row 0 \\(start 0, length 2147483648\\) does not follow on"),
        (0, 2**62, "row 0 \\(start 4611686018427387904"),
        (2, 2**62, "row 0 says 4611686018427387904 events in"),
        (2, -1, "row 0 says -1 events in"),
    ],
)
def test_an_evt_index_row_past_its_bytes_is_refused_before_any_read(
    tmp_path: Path, column: int, value: int, match: str
) -> None:
    # found by the long fuzz: a row whose length said 2**31 made the reader ask for a 2 GB buffer;
    # every row must follow on within the stored bytes, and say no more events than they can hold
    p = tmp_path / "words.h5"
    shutil.copy(_base("words"), p)
    with h5py.File(p, "r+") as f:
        [index] = [f[n] for n in _datasets(f) if n.endswith("/evt_index")]
        index[0, column] = value
    outcome, peak = run_isolated(_read_measured, p, timeout_s=DEADLINE_S, what="a damaged evt_index")
    assert outcome.startswith("TakeError TakeFormatError"), outcome
    assert re.search(match, outcome), outcome
    assert peak < MEMORY_BOUND
