"""Tail slots: where a flush puts an event sensor's rows past its last whole chunk.

The main x, y, p, t only ever receive whole chunks while recording, each compressed and
written once: HDF5 stores a rewritten compressed chunk at a new address and may hand the old
one to the next allocation while the file on disk (as of the last flush) still points there,
so a flushed partial chunk that was later completed could be lost to a kill. The partial rows
go to `tail_<col>` instead: two fixed, unfiltered, contiguous slots rewritten in place, with
the group attr `tail_meta` holding [first row, rows held] per slot. A slot is extended while
the tail's first row stays the same; when it moves, the other slot is used, so the slot the
file on disk refers to is never overwritten before the flush that replaces it completes.

The writer fills the slots (`rigd.take.sinks`); `check_repair` merges a valid one back into the
main datasets and the reader shows it on an unfinished take, both through `tail_rows`.
"""

from __future__ import annotations

import h5py
import numpy as np
from numpy.typing import NDArray

from rigd.core.layout import EVENT_DTYPES, Events


def create_tail_slots(group: h5py.Group, chunk: int) -> dict[str, h5py.Dataset]:
    """The two slots per event column, one chunk long; contiguous, so rewrites stay in place."""
    return {
        k: group.create_dataset(f"{Events.TAIL_PREFIX}{k}", shape=(2, chunk), dtype=dt, fillvalue=0)
        for k, dt in EVENT_DTYPES.items()
    }


def choose_tail_slot(meta: NDArray[np.int64], slot: int, start: int) -> int:
    """The slot to write a tail starting at row `start` to (and reset in `meta` if it is new).

    The current slot is extended when it already holds this tail; otherwise the other slot is
    taken, unless the current one is empty, so the slot the file on disk names survives.
    """
    if int(meta[slot, 0]) != start or int(meta[slot, 1]) == 0:
        slot = 1 - slot if int(meta[slot, 1]) else slot
        meta[slot] = (start, 0)
    return slot


def _tail_meta(g: h5py.Group) -> NDArray[np.int64]:
    return np.asarray(g.attrs.get(Events.TAIL_META, np.zeros((2, 2))), dtype=np.int64).reshape(-1, 2)


def tail_rows(g: h5py.Group, main_len: int) -> tuple[int, int]:
    """(slot, rows) of the flushed tail that continues the main event datasets at `main_len`;
    rows = 0 when no slot starts there (no tail, or the rows it held are in main already).

    A slot is only used if its `t` continues the main `t` without decreasing.
    """
    meta = _tail_meta(g)
    t_ds = g.get(f"{Events.TAIL_PREFIX}t")
    if not isinstance(t_ds, h5py.Dataset) or meta.shape[0] != t_ds.shape[0]:
        return 0, 0
    best = (0, 0)
    for slot, (start, n) in enumerate(meta):
        n = min(int(n), int(t_ds.shape[1]))
        if int(start) != main_len or n <= best[1]:
            continue
        t = np.asarray(t_ds[slot, :n], dtype=np.int64)
        prev = int(g[Events.T][main_len - 1]) if main_len else None
        if (prev is not None and int(t[0]) < prev) or bool((t[1:] < t[:-1]).any()):
            continue
        best = (slot, n)
    return best


def tail_end(g: h5py.Group) -> int:
    """Last row + 1 any tail slot claims (0 without tails)."""
    meta = _tail_meta(g)
    return int((meta[:, 0] + meta[:, 1]).max(initial=0)) if (meta[:, 1] > 0).any() else 0


def drop_tail_slots(g: h5py.Group) -> None:
    """Remove the slots and their attr; only once the rows they held are in the main datasets."""
    for key in EVENT_DTYPES:
        if f"{Events.TAIL_PREFIX}{key}" in g:
            del g[f"{Events.TAIL_PREFIX}{key}"]
    if Events.TAIL_META in g.attrs:
        del g.attrs[Events.TAIL_META]
