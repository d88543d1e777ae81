"""Structural checks a take passes before any reader trusts it (docs/take-format.md, "Rules a
take must follow to be read").

A take file comes from outside the daemon's trust: anyone who can write to a take directory, or
send a take, controls every byte of it. HDF5 will follow what the file says: raw data kept in
another file (external storage), a link into another file (external link), a dataset stitched
from other files (virtual dataset), soft links that loop, and dataset extents that declare
gigabytes a few bytes of file stand for. Each of those reads something the take does not hold
(a FIFO blocks the reader for good; /etc/shadow is copied into an export) or allocates without
bound, so the walk here refuses them before any dataset is read: only a regular file, only
objects stored inside it, dtypes and extents that agree with the bytes on disk.

rigd writes no external storage or virtual dataset. A multi-host take keeps each host's device
groups in that host's part file beside the joined take (rigd/take/parts.py): only there, only
directly under the groups `EXTERNAL_LINKS_ALLOWED` names, only to a part file the take's own
manifest lists as linked, only to the same HDF5 path in it, and only when that name is a regular
file inside the take's own directory (`check_link`). A part file itself holds no link at all.
The walk never follows a link: readers open the part explicitly once it passed these checks
(rigd/take/linked.py), so HDF5's own search path for link targets (HDF5_EXT_PREFIX, the working
directory) never comes into play.
"""

from __future__ import annotations

import logging
import os
import stat
from pathlib import Path, PurePosixPath

import h5py
import numpy as np

from rigd.core.errors import TakeFormatError
from rigd.take.manifest import linked_files, read_manifest

log = logging.getLogger(__name__)

#: Groups whose members may be external links, in a joined multi-host take only: a device's
#: group kept in its host's part file (see the module docstring).
EXTERNAL_LINKS_ALLOWED: frozenset[str] = frozenset({"/events", "/frames"})
#: More objects than any rig writes (a few per device); bounds the walk of a hostile file.
MAX_OBJECTS = 4096
#: Deeper than any take's layout (/events/<sensor>/trigger/<series> is 4).
MAX_DEPTH = 8
#: Dimensions of the largest dataset a take holds (images: N, H, W, C).
MAX_NDIM = 4
#: How far a chunked dataset's declared size may exceed its stored bytes. Deflate can't
#: compress beyond ~1032:1 and LZ4 beyond ~255:1; Zstd can, but no rig data compresses that
#: far. A dataset declaring more is mostly chunks never written, which every read would
#: allocate and fill.
MAX_RATIO = 1100
#: A dataset this small (declared bytes) is let through whatever it stores.
SMALL_BYTES = 1 << 20
#: Datasets a reader reads whole (indexes and per-frame / per-pulse series, not images or event
#: columns, which it reads in blocks) may declare at most this much beyond `WHOLE_RATIO` times
#: what they store: what one read of them allocates stays bounded whatever they compress to.
WHOLE_READ_BYTES = 256 << 20
WHOLE_RATIO = 64
_WHOLE_NAMES = frozenset(
    {
        "evt_index",
        "t_exposure_start_us",
        "t_exposure_start_device_us",
        "exposure_us",
        "frame_counter",
        "pulse_index",
        "journal_json",
    }
)
_WHOLE_GROUPS = frozenset({"trigger", "pulses"})
#: dtype kinds a take stores: signed, unsigned, float, bool; strings are checked apart.
_KINDS = frozenset("iufb")


def check_regular_file(path: Path) -> os.stat_result:
    """The take must be a regular file: a FIFO, device or directory named like a take would
    block or mislead the reader. A symbolic link is followed, and its target must be one."""
    try:
        st = os.stat(path)
    except FileNotFoundError as exc:
        raise TakeFormatError(f"{path}: no such take file") from exc
    except OSError as exc:
        raise TakeFormatError(f"{path}: cannot be read: {exc.strerror}") from exc
    if not stat.S_ISREG(st.st_mode):
        raise TakeFormatError(f"{path}: is not a regular file (a take is one HDF5 file)")
    return st


def check_link_target(path: Path, hpath: str, filename: str) -> Path:
    """An external link's target must be a relative name inside the take's directory that is a
    regular file other than the take itself; returns its path."""
    rel = PurePosixPath(filename)
    if rel.is_absolute() or ".." in rel.parts or not rel.parts:
        raise TakeFormatError(f"{path}: {hpath}: external link to {filename!r} leaves the take's directory")
    target = path.parent / rel
    resolved = target.resolve()
    if resolved.parent != path.parent.resolve():
        raise TakeFormatError(f"{path}: {hpath}: external link to {filename!r} leaves the take's directory")
    if resolved == path.resolve():
        raise TakeFormatError(f"{path}: {hpath}: external link to {filename!r} leads back to the take itself")
    if not os.path.lexists(target):
        raise TakeFormatError(
            f"{path}: {hpath}: its part {filename} is not in the take's directory (a multi-host take moves "
            "with its part files; `rigd takes gather` fetches a missing one)"
        )
    check_regular_file(target)
    return target


def check_link(path: Path, hpath: str, link: h5py.ExternalLink, files: frozenset[str]) -> Path:
    """Whether the external link at `hpath` of the take at `path` is one the multi-host layout
    allows (`files`: the part files its manifest lists as linked); returns the part's path."""
    parent = hpath.rsplit("/", 1)[0]
    if parent not in EXTERNAL_LINKS_ALLOWED or not files:
        raise TakeFormatError(
            f"{path}: {hpath}: is an external link (to {link.filename!r}:{link.path!r}); a take holds none "
            "(only a joined take's /events/<sensor> and /frames/<camera> link to its parts)"
        )
    if link.filename not in files:
        raise TakeFormatError(
            f"{path}: {hpath}: external link to {link.filename!r}, which the take's parts manifest does "
            "not list as a linked part"
        )
    if link.path != hpath:
        raise TakeFormatError(
            f"{path}: {hpath}: external link to {link.path!r} in its part; a device's group is linked "
            "to the same path in its part"
        )
    return check_link_target(path, hpath, link.filename)


def check_structure(f: h5py.File, path: Path, size: int | None = None, *, part: bool = False) -> None:
    """Walk every link and object of an open take without reading any dataset's data; raise
    TakeFormatError naming the file and HDF5 object at the first that breaks a rule. `size`:
    the length HDF5 sees (a truncated take's zero-padded view), else the file's. `part`: the file
    is a multi-host take's part, which holds no link and is no joined take itself."""
    file_size = size if size is not None else os.stat(path).st_size
    try:
        _Walk(f, path, file_size, part).run()
    except (OSError, RuntimeError, ValueError, KeyError, TypeError, AttributeError) as exc:
        # HDF5 refusing an object header or link table is damage too, named like the rest
        why = describe(exc)
        if "addr overflow" in why:  # a header recording an end before what it points to
            raise TakeFormatError(
                f"{path}: damaged by a failed write (disk full before the first flush?): HDF5 "
                f"refuses its structure ({why}) and `rigd recover` cannot repair it"
            ) from exc
        raise TakeFormatError(f"{path}: damaged, its structure cannot be read (HDF5: {why})") from exc


class _Walk:
    def __init__(self, f: h5py.File, path: Path, file_size: int | None, part: bool = False) -> None:
        self.f = f
        self.path = path
        self.file_size = file_size
        self.part = part
        self.links: frozenset[str] = frozenset()
        self.seen: set[int] = set()

    def fail(self, hpath: str, msg: str) -> TakeFormatError:
        return TakeFormatError(f"{self.path}: {hpath}: {msg}")

    def run(self) -> None:
        self.attrs(self.f, "/")
        manifest = read_manifest(self.f, self.path)
        if manifest is not None and self.part:
            raise self.fail("/", "a part of a multi-host take is itself a joined take (attr parts_json)")
        self.links = linked_files(manifest)
        self.group(self.f, "/", 0)

    def visit(self, obj: h5py.HLObject, hpath: str) -> bool:
        """False when the object was seen already (a hard link to it elsewhere, or a cycle)."""
        addr = h5py.h5o.get_info(obj.id).addr
        if addr in self.seen:
            return False
        if len(self.seen) >= MAX_OBJECTS:
            raise self.fail(hpath, f"more than {MAX_OBJECTS} objects; no take holds that many")
        self.seen.add(addr)
        return True

    def group(self, g: h5py.Group, hpath: str, depth: int) -> None:
        if depth > MAX_DEPTH:
            raise self.fail(hpath, f"nested deeper than {MAX_DEPTH} groups; no take is")
        for name in g:
            child = f"{hpath.rstrip('/')}/{name}"
            link = g.get(name, getlink=True)
            if isinstance(link, h5py.SoftLink):
                raise self.fail(child, f"is a soft link (to {link.path!r}); a take holds none")
            if isinstance(link, h5py.ExternalLink):
                if self.part:
                    raise self.fail(
                        child,
                        f"is an external link (to {link.filename!r}:{link.path!r}); a part of a multi-host "
                        "take holds none",
                    )
                check_link(self.path, child, link, self.links)
                continue
            if not isinstance(link, h5py.HardLink):
                raise self.fail(child, f"is a link of unknown kind ({type(link).__name__})")
            node = g.get(name)
            if node is None:  # listed, but its object cannot be opened
                raise self.fail(child, "is listed but cannot be opened (a damaged object header)")
            if not self.visit(node, child):
                continue
            self.attrs(node, child)
            if isinstance(node, h5py.Group):
                self.group(node, child, depth + 1)
            elif isinstance(node, h5py.Dataset):
                self.dataset(node, child)
            else:
                raise self.fail(child, f"is a {type(node).__name__}, not a group or dataset")

    def attrs(self, obj: h5py.HLObject, hpath: str) -> None:
        for name in obj.attrs:
            info = obj.attrs.get_id(name)
            dt = info.dtype
            if dt.kind not in _KINDS and h5py.check_string_dtype(dt) is None:
                raise self.fail(hpath, f"attribute {name!r} has dtype {dt}; a take stores numbers and text")
            if len(info.shape) > 2:
                raise self.fail(hpath, f"attribute {name!r} has shape {info.shape}; a take's are at most 2-D")
            if info.get_storage_size() > SMALL_BYTES:
                raise self.fail(hpath, f"attribute {name!r} holds {info.get_storage_size():,} bytes")

    def dataset(self, ds: h5py.Dataset, hpath: str) -> None:
        dcpl = ds.id.get_create_plist()
        layout = dcpl.get_layout()
        if layout == h5py.h5d.VIRTUAL:
            raise self.fail(hpath, "is a virtual dataset (its data lives in other files); a take holds none")
        if dcpl.get_external_count() > 0:
            name = dcpl.get_external(0)[0].decode("utf-8", "replace")
            raise self.fail(hpath, f"keeps its data in an external file ({name!r}); a take holds none")
        dt = ds.dtype
        if dt.kind not in _KINDS and h5py.check_string_dtype(dt) is None:
            raise self.fail(hpath, f"has dtype {dt}; a take stores numbers and text")
        if ds.ndim > MAX_NDIM:
            raise self.fail(hpath, f"has {ds.ndim} dimensions; a take's datasets have at most {MAX_NDIM}")
        if h5py.check_string_dtype(dt) is not None and ds.ndim != 0:
            raise self.fail(hpath, f"is text of shape {ds.shape}; a take's text datasets are scalars")
        declared = int(np.prod(ds.shape, dtype=object)) * dt.itemsize
        stored = int(ds.id.get_storage_size())
        if layout == h5py.h5d.CONTIGUOUS:
            self.contiguous(ds, hpath, declared, stored)
        elif layout == h5py.h5d.CHUNKED:
            self.chunked(ds, hpath, declared, stored)

    def contiguous(self, ds: h5py.Dataset, hpath: str, declared: int, stored: int) -> None:
        if h5py.check_string_dtype(ds.dtype) is not None and ds.dtype.kind == "O":
            return  # variable-length text: the bytes live on the global heap, bounded by the file
        if declared > SMALL_BYTES and stored != declared:
            raise self.fail(hpath, f"declares {declared:,} bytes but stores {stored:,}")
        offset = ds.id.get_offset()
        if offset is not None and self.file_size is not None and offset + stored > self.file_size:
            raise self.fail(
                hpath,
                f"its data (bytes {offset:,}-{offset + stored:,}) lies past the end of the file "
                f"({self.file_size:,} bytes)",
            )

    def chunked(self, ds: h5py.Dataset, hpath: str, declared: int, stored: int) -> None:
        parts = hpath.split("/")
        whole = parts[-1] in _WHOLE_NAMES or (len(parts) > 2 and parts[-2] in _WHOLE_GROUPS)
        if whole and declared > max(WHOLE_READ_BYTES, stored * WHOLE_RATIO):
            raise self.fail(
                hpath,
                f"declares {declared:,} bytes of data (shape {ds.shape}, {ds.dtype}) in {stored:,} stored: "
                f"more than {WHOLE_RATIO}x beyond {WHOLE_READ_BYTES >> 20} MiB for a dataset read whole",
            )
        if declared > SMALL_BYTES and declared > stored * MAX_RATIO:
            raise self.fail(
                hpath,
                f"declares {declared:,} bytes of data (shape {ds.shape}, {ds.dtype}) but stores "
                f"{stored:,}: more than {MAX_RATIO}x, chunks that were never written",
            )


def describe(exc: BaseException) -> str:
    """The first line of an exception, for a one-line error."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__
