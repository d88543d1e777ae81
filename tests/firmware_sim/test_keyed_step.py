"""The keyed step's threaded and serial passes: one source each, compiled twice, cached apart.

That they give the same events is `test_event_model`'s
`test_parallel_serial_and_reference_give_the_same_events`.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import pytest

from firmware_sim import keyed_step

TWINS = [
    (keyed_step._emit, keyed_step._emit_par, keyed_step._emit_ser),
    (keyed_step._sort, keyed_step._sort_par, keyed_step._sort_ser),
]


@pytest.mark.parametrize(("source", "par", "ser"), TWINS, ids=["emit", "sort"])
def test_both_variants_are_compiled_from_one_source(source: Any, par: Any, ser: Any) -> None:
    assert par.py_func.__code__ is source.__code__
    assert ser.py_func.__code__ is source.__code__
    assert par.targetoptions["parallel"] is True
    assert not ser.targetoptions.get("parallel")


@pytest.mark.parametrize(("source", "par", "ser"), TWINS, ids=["emit", "sort"])
def test_the_variants_have_cache_entries_of_their_own(source: Any, par: Any, ser: Any) -> None:
    index = [d._cache._cache_file._index_path for d in (par, ser)]
    assert index[0] != index[1]


KERNEL = """
import numpy as np
from numba import get_thread_id, prange
from numba.np.ufunc.parallel import _launch_threads

from firmware_sim.keyed_step import _threaded_and_serial

def _threads(out):
    for i in prange(out.shape[0]):
        out[i] = get_thread_id()

threads_par, threads_ser = _threaded_and_serial(_threads)

if __name__ == "__main__":
    import sys
    _launch_threads()  # get_thread_id in code loaded from the cache wants the pool up
    for name in sys.argv[1]:
        kernel = threads_par if name == "p" else threads_ser
        out = np.zeros(1 << 16, np.int64)
        kernel(out)
        print(name, len(set(out.tolist())), sum(kernel.stats.cache_hits.values()))
"""


@pytest.mark.slow
def test_a_variant_loaded_from_the_cache_is_still_itself(tmp_path: Path) -> None:
    """Compiled in one process (serial first), loaded in the next: the threaded variant runs
    on more than one thread and the serial on one (sharing an entry, one would load the other)."""
    module = tmp_path / "twins.py"
    module.write_text(textwrap.dedent(KERNEL))
    env = {
        **os.environ,
        "NUMBA_CACHE_DIR": str(tmp_path / "cache"),
        "NUMBA_NUM_THREADS": "2",
        "PYTHONPATH": os.pathsep.join([str(Path(keyed_step.__file__).parents[1]), str(tmp_path)]),
    }

    def run(order: str) -> list[tuple[str, int, int]]:
        done = subprocess.run(
            [sys.executable, str(module), order],
            env=env,
            capture_output=True,
            text=True,
            check=True,
            timeout=300,
        )
        return [(n, int(t), int(h)) for n, t, h in (line.split() for line in done.stdout.splitlines())]

    assert run("sp") == [("s", 1, 0), ("p", 2, 0)]
    assert run("sp") == [("s", 1, 1), ("p", 2, 1)]
