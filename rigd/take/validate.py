"""Schema validation of take files: a list of problems, each naming the HDF5 path.

Large datasets are scanned in blocks, so validating a multi-hour take needs constant
memory. A file that cannot be read at all yields one problem, never a traceback.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import h5py
import hdf5plugin  # noqa: F401  (registers the LZ4 / Zstd filters with h5py)
import numpy as np
from numpy.typing import NDArray
from pydantic import ValidationError

from rigd.core.errors import TakeFormatError
from rigd.core.layout import (
    EVENT_DTYPES,
    EVENTS_GROUP,
    FRAME_SERIES,
    FRAMES_GROUP,
    PULSE_SERIES,
    PULSES_PATH,
    ROOT_ATTRS,
    SYNC_REPORT_PATH,
    TRIGGER_DTYPES,
    Device,
    Events,
    Frames,
    Root,
    Status,
    TimeDomain,
)
from rigd.core.pixels import stored_pixel_format
from rigd.core.schema import SCHEMA_NAME, SCHEMA_VERSION, SyncReport, decode_journal, has_item
from rigd.take.evt_read import is_evt_words
from rigd.take.evt_validate import check_evt_words
from rigd.take.h5file import attr_text
from rigd.take.linked import TakeH5

log = logging.getLogger(__name__)

_BLOCK = 1 << 20


class _Validator:
    def __init__(self, path: Path, h: TakeH5) -> None:
        self.path = path
        self.h = h  # resolves a joined take's links into its part files
        self.f = f = h.file
        self.problems: list[str] = []
        self.version = attr_text(f.attrs.get(Root.SCHEMA_VERSION, SCHEMA_VERSION))

    def add(self, hpath: str, msg: str) -> None:
        self.problems.append(f"{self.path}: {hpath}: {msg}")

    @contextmanager
    def reading(self, hpath: str) -> Iterator[None]:
        """Turn a read failure (corrupt chunk, missing filter, odd types) into a problem."""
        try:
            yield
        except TakeFormatError as exc:  # a joined take's part refused by the link checks
            self.problems.append(str(exc))
        except (OSError, ValueError, TypeError, KeyError) as exc:
            self.add(hpath, f"cannot be read: {type(exc).__name__}: {exc}")

    def dataset(self, hpath: str, dtype: Any | None = None, ndim: int | None = 1) -> h5py.Dataset | None:
        node = self.h.get(hpath)
        if node is None:
            self.add(f"/{hpath}", "missing")
            return None
        if not isinstance(node, h5py.Dataset):
            self.add(f"/{hpath}", "is not a dataset")
            return None
        if dtype is not None and node.dtype != np.dtype(dtype):
            self.add(f"/{hpath}", f"dtype {node.dtype}, expected {np.dtype(dtype)}")
            return None
        if ndim is not None and node.ndim != ndim:
            self.add(f"/{hpath}", f"has {node.ndim} dimensions, expected {ndim}")
            return None
        return node

    def group(self, hpath: str) -> h5py.Group | None:
        node = self.h.get(hpath)
        if not isinstance(node, h5py.Group):
            self.add(f"/{hpath}", "missing group" if node is None else "is not a group")
            return None
        return node

    def equal_lengths(self, hpath: str, dsets: dict[str, h5py.Dataset | None]) -> None:
        lengths = {k: int(d.shape[0]) for k, d in dsets.items() if d is not None}
        if len(set(lengths.values())) > 1:
            desc = ", ".join(f"{k}={n}" for k, n in lengths.items())
            self.add(f"/{hpath}", f"datasets have unequal lengths ({desc})")

    # -- checks ------------------------------------------------------------------------
    def run(self) -> None:
        f = self.f
        attrs = {k: attr_text(f.attrs[k]) for k in ROOT_ATTRS if k in f.attrs}
        for k in ROOT_ATTRS:
            if k not in attrs:
                self.add("/", f"missing attribute {k!r}")
        if Root.SCHEMA in attrs and attrs[Root.SCHEMA] != SCHEMA_NAME:
            self.add("/", f"attribute schema is {attrs['schema']!r}, expected {SCHEMA_NAME!r}")
        if Root.SCHEMA_VERSION in attrs:
            major = attrs[Root.SCHEMA_VERSION].split(".")[0]
            if major != SCHEMA_VERSION.split(".")[0]:
                self.add(
                    "/", f"schema_version {attrs['schema_version']!r} is not {SCHEMA_VERSION.split('.')[0]}.x"
                )
        status = attrs.get(Root.STATUS)
        domain = attrs.get(Root.TIME_DOMAIN)
        if status is not None and status not in (Status.RECORDING, Status.COMPLETE, Status.FAILED):
            self.add("/", f"status {status!r} is not recording, complete or failed")
        if domain is not None and domain not in (TimeDomain.DEVICE, TimeDomain.RIG):
            self.add("/", f"time_domain {domain!r} is not device or rig")
        if status == Status.COMPLETE and domain != TimeDomain.RIG:
            self.add("/", f"status is complete but time_domain is {domain!r}, expected 'rig'")
        if status != Status.COMPLETE and (
            Root.FINALIZE_STARTED_UTC in f.attrs or Root.FINALIZE_PLAN in f.attrs
        ):
            self.add(
                "/",
                "finalize was interrupted: stored times may be partly mapped to rig time "
                "(`rigd recover` finishes it exactly)",
            )
        if Root.TRUNCATED_EOF in f.attrs:
            self.add("/", "a repair of this truncated take was interrupted (run `rigd recover` again)")
        rig = domain == TimeDomain.RIG
        self.check_config()
        with self.reading(f"/{Root.JOURNAL}"):
            self.check_journal()
        if Root.RECOVERY_REPORT in f.attrs:
            with self.reading("/"):
                if not isinstance(json.loads(attr_text(f.attrs[Root.RECOVERY_REPORT])), dict):
                    self.add("/", f"attribute {Root.RECOVERY_REPORT} is not a JSON object")
        ev = f.get(EVENTS_GROUP)
        if self.group(EVENTS_GROUP) is not None and isinstance(ev, h5py.Group):
            for name in ev:
                with self.reading(f"/{EVENTS_GROUP}/{name}"):
                    self.check_sensor(name, rig)
        fr = f.get(FRAMES_GROUP)
        if self.group(FRAMES_GROUP) is not None and isinstance(fr, h5py.Group):
            for name in fr:
                with self.reading(f"/{FRAMES_GROUP}/{name}"):
                    self.check_camera(name)
        with self.reading(f"/{PULSES_PATH}"):
            self.check_pulses()
        if status == "complete":
            with self.reading(f"/{SYNC_REPORT_PATH}"):
                self.check_report()
        if self.h.manifest is not None:
            with self.reading(f"/ attr {Root.PARTS}"):
                self.check_parts()

    def check_config(self) -> None:
        ds = self.dataset(Root.CONFIG, ndim=0)
        if ds is None:
            return
        with self.reading(f"/{Root.CONFIG}"):
            data = json.loads(attr_text(ds[()]))
            if not isinstance(data, dict):
                self.add(f"/{Root.CONFIG}", "is not a JSON object")

    def check_journal(self) -> None:
        if Root.JOURNAL not in self.f:
            return  # optional: only takes whose writer was given a journal have one
        ds = self.dataset(Root.JOURNAL, np.uint8, ndim=2)
        if ds is not None and (ds.shape[0] != 2 or decode_journal(ds[...]) is None):
            self.add(f"/{Root.JOURNAL}", "has no readable slot (expected 2 rows of NUL-padded JSON)")

    def check_report(self) -> None:
        ds = self.dataset(SYNC_REPORT_PATH, ndim=0)
        if ds is None:
            return
        try:
            SyncReport.model_validate_json(attr_text(ds[()]))
        except ValidationError as exc:
            self.add(f"/{SYNC_REPORT_PATH}", f"does not parse as a SyncReport: {exc}")

    def check_sensor(self, name: str, rig: bool) -> None:
        base = f"{EVENTS_GROUP}/{name}"
        g = self.group(base)
        if g is None:
            return
        dims: dict[str, int] = {}
        for key in (Device.WIDTH, Device.HEIGHT):
            if key not in g.attrs:
                self.add(f"/{base}", f"missing attribute {key!r}")
            else:
                value = int(g.attrs[key])
                if value <= 0:
                    self.add(f"/{base}", f"attribute {key} is {value}, expected > 0")
                else:
                    dims[key] = value
        if is_evt_words(g):
            for hpath, msg in check_evt_words(g, rig):
                self.add(hpath, msg)
            cols = {}
        else:
            cols = {k: self.dataset(f"{base}/{k}", dt) for k, dt in EVENT_DTYPES.items()}
            self.equal_lengths(base, cols)
        off = self.dataset(f"{base}/{Events.T_OFFSET}", np.int64, ndim=0)
        ms = (
            self.dataset(f"{base}/{Events.MS_TO_IDX}", np.uint64)
            if cols and (rig or Events.MS_TO_IDX in g)
            else None
        )
        tg = self.group(f"{base}/{Events.TRIGGER}")
        if tg is not None:
            # Items a newer minor version added are optional in older takes (1.0: host_time_ns).
            trig = {
                k: self.dataset(f"{base}/trigger/{k}", dt)
                for k, dt in TRIGGER_DTYPES.items()
                if k in tg or has_item(self.version, f"{Events.TRIGGER}/{k}")
            }
            self.equal_lengths(f"{base}/{Events.TRIGGER}", trig)
        if (
            not cols
            or any(d is None for d in cols.values())
            or len({int(d.shape[0]) for d in cols.values() if d}) != 1
        ):
            return
        self.scan_events(base, cols, dims, ms if off is not None else None)

    def scan_events(
        self,
        base: str,
        cols: dict[str, h5py.Dataset | None],
        dims: dict[str, int],
        ms: h5py.Dataset | None,
    ) -> None:
        """One blockwise pass: t order, geometry, polarity values, and the ms_to_idx index."""
        t_ds, x_ds, y_ds, p_ds = (cols[k] for k in (Events.T, Events.X, Events.Y, Events.P))
        assert t_ds is not None
        assert x_ds is not None
        assert y_ds is not None
        assert p_ds is not None
        n = int(t_ds.shape[0])
        found: set[str] = set()
        prev: int | None = None
        n_ms = int(ms.shape[0]) if ms is not None else 0
        if ms is not None:
            last = int(t_ds[n - 1]) if n else -1
            expect = last // 1000 + 1 if last >= 0 else 0
            if n_ms != expect:
                self.add(
                    f"/{base}/{Events.MS_TO_IDX}", f"has {n_ms} entries, expected {expect} (last t {last} us)"
                )
                ms = None
        ms_next = 0
        for start in range(0, n, _BLOCK):
            stop = min(start + _BLOCK, n)
            t: NDArray[np.int64] = t_ds[start:stop]
            if "t" not in found:
                if prev is not None and int(t[0]) < prev:
                    found.add("t")
                    self.add(f"/{base}/t", f"decreases at index {start} ({int(t[0])} < {prev})")
                bad = np.flatnonzero(t[1:] < t[:-1])
                if bad.size and "t" not in found:
                    i = int(bad[0]) + 1
                    found.add("t")
                    self.add(f"/{base}/t", f"decreases at index {start + i} ({int(t[i])} < {int(t[i - 1])})")
            prev = int(t[-1])
            for axis, ds, key in (("x", x_ds, Device.WIDTH), ("y", y_ds, Device.HEIGHT)):
                if axis in found or key not in dims:
                    continue
                arr = ds[start:stop]
                if int(arr.max()) >= dims[key]:
                    i = int(np.argmax(arr >= dims[key]))
                    found.add(axis)
                    self.add(
                        f"/{base}/{axis}",
                        f"value {int(arr[i])} at index {start + i} outside {key} {dims[key]}",
                    )
            if "p" not in found:
                p = p_ds[start:stop]
                if int(p.max()) > 1:
                    found.add("p")
                    i = int(np.argmax(p > 1))
                    self.add(f"/{base}/p", f"value {int(p[i])} at index {start + i}, expected 0 or 1")
            if ms is not None and "t" not in found and "ms" not in found:
                ms_hi = min(int(t[-1]) // 1000 + 1, n_ms) if t[-1] >= 0 else 0
                while ms_next < ms_hi:
                    hi = min(ms_next + _BLOCK, ms_hi)
                    want = np.searchsorted(t, np.arange(ms_next, hi, dtype=np.int64) * 1000) + start
                    have = ms[ms_next:hi].astype(np.int64)
                    wrong = np.flatnonzero(have != want)
                    if wrong.size:
                        i = int(wrong[0])
                        found.add("ms")
                        self.add(
                            f"/{base}/{Events.MS_TO_IDX}",
                            f"entry {ms_next + i} is {int(have[i])}, expected {int(want[i])} "
                            f"(first index with t >= {(ms_next + i) * 1000} us)",
                        )
                        break
                    ms_next = hi

    def check_camera(self, name: str) -> None:
        base = f"{FRAMES_GROUP}/{name}"
        g = self.group(base)
        if g is None:
            return
        for key in (Device.HEIGHT, Device.WIDTH):
            if key not in g.attrs:
                self.add(f"/{base}", f"missing attribute {key!r}")
        images = self.dataset(f"{base}/images", ndim=None)
        if images is not None and images.ndim not in (3, 4):
            self.add(f"/{base}/images", f"has {images.ndim} dimensions, expected 3 (N,H,W) or 4 (N,H,W,C)")
            images = None
        if images is not None:
            try:
                stored_pixel_format(g.attrs, tuple(images.shape[1:]), f"/{base}")
            except TakeFormatError as exc:
                self.add(f"/{base}", str(exc).removeprefix(f"/{base}: "))
        series: dict[str, h5py.Dataset | None] = {
            k: self.dataset(f"{base}/{k}", np.int64) for k in FRAME_SERIES
        }
        self.equal_lengths(base, {Frames.IMAGES: images, **series})
        for key in (Frames.T_EXPOSURE_START, Frames.T_EXPOSURE_START_DEVICE):
            ds = series[key]
            if ds is None:
                continue
            ts = ds[...]
            bad = np.flatnonzero(ts[1:] < ts[:-1])
            if bad.size:
                i = int(bad[0]) + 1
                self.add(f"/{base}/{key}", f"decreases at frame {i} ({int(ts[i])} < {int(ts[i - 1])})")

    def check_parts(self) -> None:
        """A joined take: each linked part holds its devices, and every device group is in the
        part the manifest gives it (the link checks themselves ran when the file was opened)."""
        owner: dict[str, str] = {}
        for entry in self.h.manifest or ():
            for device in entry.devices:
                if device in owner:
                    self.add(
                        f"/ attr {Root.PARTS}",
                        f"device {device} is in the parts of {owner[device]} and {entry.host}",
                    )
                owner[device] = entry.host
            if not entry.linked:
                continue
            for device in entry.devices:
                hpath = next(
                    (f"/{g}/{device}" for g in (EVENTS_GROUP, FRAMES_GROUP) if device in self.f.get(g, {})),
                    None,
                )
                if hpath is None:
                    self.add(
                        f"/ attr {Root.PARTS}", f"host {entry.host}: device {device} has no group in the take"
                    )
                    continue
                link = self.f[hpath.rsplit("/", 1)[0]].get(device, getlink=True)
                if not isinstance(link, h5py.ExternalLink) or link.filename != entry.file:
                    self.add(hpath, f"is not linked to its part {entry.file} (host {entry.host})")

    def check_pulses(self) -> None:
        base = PULSES_PATH
        if self.group(base) is None:
            return
        dsets: dict[str, h5py.Dataset | None] = {
            k: self.dataset(f"{base}/{k}", np.int64) for k in PULSE_SERIES
        }
        self.equal_lengths(base, dsets)


def validate_take(path: str | Path) -> list[str]:
    """Problems found in a take file, each naming the file and HDF5 path; [] if it is valid."""
    p = Path(path)
    try:
        h = TakeH5(p, "r")
    except TakeFormatError as exc:
        return [str(exc)]
    with h:
        v = _Validator(p, h)
        with v.reading("/"):
            v.run()
    if v.problems:
        log.info("take %s: %d problem(s)", p, len(v.problems))
    return v.problems
