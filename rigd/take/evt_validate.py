"""Validation of an "evt_words" event sensor: its index follows its words, and every row
decodes to the events the index says, inside the sensor's geometry and in time order."""

from __future__ import annotations

import h5py
import numpy as np

from rigd.core.errors import TakeFormatError
from rigd.core.layout import EVT_INDEX_COLUMNS, Device, Events
from rigd.take.evt_read import EvtWordsEvents, consistent_rows

#: Index rows decoded per step (bounded memory: about 128 KiB of words each).
_ROWS_PER_STEP = 256


def check_evt_words(g: h5py.Group, rig: bool) -> list[tuple[str, str]]:
    """(HDF5 path, problem) pairs; empty for a sound sensor."""
    base = g.name
    out: list[tuple[str, str]] = []
    words, index = g.get(Events.EVT_WORDS), g.get(Events.EVT_INDEX)
    for key, node in ((Events.EVT_WORDS, words), (Events.EVT_INDEX, index)):
        if not isinstance(node, h5py.Dataset):
            out.append((f"{base}/{key}", "missing"))
    for key in (Events.EVT_FORMAT, Device.WIDTH, Device.HEIGHT):
        if key not in g.attrs:
            out.append((base, f"missing attribute {key!r}"))
    if rig and Events.CLOCK_MAP not in g.attrs:
        out.append((base, f"missing attribute {Events.CLOCK_MAP!r} (finalized take)"))
    if out or not isinstance(words, h5py.Dataset) or not isinstance(index, h5py.Dataset):
        return out
    if index.ndim != 2 or index.shape[1] <= len(EVT_INDEX_COLUMNS):
        return [
            (
                f"{base}/{Events.EVT_INDEX}",
                f"shape {index.shape}, expected (rows, > {len(EVT_INDEX_COLUMNS)})",
            )
        ]
    rows = np.asarray(index[...], dtype=np.int64)
    n_bytes = int(words.shape[0])
    good = consistent_rows(rows, n_bytes)
    if good < rows.shape[0]:
        out.append(
            (f"{base}/{Events.EVT_INDEX}", f"row {good} does not follow on or ends past the {n_bytes} bytes")
        )
        return out
    end = int(rows[-1, 0] + rows[-1, 1]) if rows.shape[0] else 0
    if end != n_bytes:
        out.append((f"{base}/{Events.EVT_WORDS}", f"{n_bytes} bytes, the index covers {end}"))
    reader = EvtWordsEvents(g, g.file.filename, None)
    prev = None
    for r0 in range(0, rows.shape[0], _ROWS_PER_STEP):
        r1 = min(r0 + _ROWS_PER_STEP, rows.shape[0])
        try:
            ev = reader.decode_rows(r0, r1)
        except TakeFormatError as exc:
            out.append((f"{base}/{Events.EVT_INDEX}", str(exc).split(": ", 2)[-1]))
            return out
        if len(ev):
            if (prev is not None and int(ev.t[0]) < prev) or bool((ev.t[1:] < ev.t[:-1]).any()):
                out.append((f"{base}/{Events.EVT_WORDS}", f"event times decrease in rows [{r0}, {r1})"))
                return out
            prev = int(ev.t[-1])
    return out
