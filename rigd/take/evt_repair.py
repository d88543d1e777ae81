"""Crash repair of an "evt_words" event sensor: index rows past the stored bytes are cut, and
bytes past the last row.

While recording, evt_words receives whole chunks only and its extent runs ahead of the data;
a flush puts the partial last chunk in a tail slot and appends the closed index rows. After a
kill, the bytes really stored are the chunks present from the start (`stored_prefix`) plus the
tail slot that continues them; the index is kept up to its last row that starts where the
previous one ended and ends within those bytes. The rows cut are reported with the events they
held, the bytes past the last row kept (no row says what they decode to) as words cut.
"""

from __future__ import annotations

from dataclasses import dataclass

import h5py
import numpy as np
from numpy.typing import NDArray

from rigd.core.layout import Events
from rigd.take.evt_read import consistent_rows
from rigd.take.evt_sink import drop_words_tail, words_tail


@dataclass(frozen=True, slots=True)
class EvtCut:
    """What repair keeps of one evt_words sensor."""

    rows_before: int
    rows_kept: int
    bytes_stored: int
    """Bytes really in the file: whole chunks from the start, then the tail that continues them."""
    bytes_kept: int
    events_lost: int
    reasons: list[str]
    tail: NDArray[np.uint8]
    main: int


def plan_evt_cut(g: h5py.Group, main: int, index_stored: int, *, finalizing: bool) -> EvtCut:
    """`main`: bytes of evt_words in chunks present from the start; `index_stored`: index rows
    likewise. `finalizing`: a finalize had started (all data flushed, tails merged): no tail."""
    index = g[Events.EVT_INDEX]
    tail = np.empty(0, np.uint8) if finalizing else words_tail(g, main)
    available = main + tail.shape[0]
    ncol = int(index.shape[1])
    rows = np.asarray(index[:index_stored], dtype=np.int64).reshape(-1, ncol)
    keep = consistent_rows(rows, available)
    end = int(rows[keep - 1, 0] + rows[keep - 1, 1]) if keep else 0
    before = int(index.shape[0])
    cut = np.asarray(index[keep:before], dtype=np.int64).reshape(-1, ncol) if keep < before else None
    lost = int(cut[:, 2].clip(min=0).sum()) if cut is not None else 0
    reasons = []
    if keep < before:
        reasons.append(
            f"evt_index rows past the {available} stored bytes or not following on (kill mid-flush)"
        )
    if available > end:
        reasons.append(
            f"{available - end} EVT byte(s) past the last index row (no row says what they decode to)"
        )
    return EvtCut(before, keep, available, end, lost, reasons, tail, main)


def apply_evt_cut(g: h5py.Group, cut: EvtCut) -> None:
    """Merge the tail that the kept rows need into evt_words, trim both datasets, drop the tail."""
    words, index = g[Events.EVT_WORDS], g[Events.EVT_INDEX]
    if int(words.shape[0]) != cut.bytes_kept:
        words.resize((cut.bytes_kept,))
    if cut.bytes_kept > cut.main:
        words[cut.main : cut.bytes_kept] = cut.tail[: cut.bytes_kept - cut.main]  # one new chunk
    if int(index.shape[0]) != cut.rows_kept:
        index.resize((cut.rows_kept, index.shape[1]))
    drop_words_tail(g)


def kept_rows(g: h5py.Group, kept: dict[str, int]) -> NDArray[np.int64]:
    """The index rows a (dry-run) repair keeps."""
    index = g[Events.EVT_INDEX]
    n = kept.get(g.name, int(index.shape[0]))
    return np.asarray(index[:n], dtype=np.int64).reshape(-1, index.shape[1])
