"""A take's HDF5 file together with the part files a multi-host take's device groups link to.

A joined take (rigd/take/parts.py) keeps `/events/<sensor>` and `/frames/<camera>` as HDF5
external links into the part files beside it. HDF5 would follow such a link by its own search
(the HDF5_EXT_PREFIX variable, then the directory of the file, then the working directory), so
a name that is safe beside the take could still be resolved to another file. Readers therefore
never hand a path through a link to h5py: `TakeH5.get` walks the path one link at a time and,
at an external link, checks it (`rigd.take.structure.check_link`: allowed place, a part the
manifest lists, a regular file in the take's own directory) and opens that file itself, with
the same structure checks as any take plus "holds no link" (a link loop or a chain of parts is
refused there). A take that is not joined reads exactly as before.
"""

from __future__ import annotations

import logging
from pathlib import Path
from types import TracebackType
from typing import Any, Self

import h5py

from rigd.core.errors import TakeFormatError
from rigd.take.h5file import check_header, open_checked
from rigd.take.manifest import PartEntry, linked_files, read_manifest
from rigd.take.structure import check_link

log = logging.getLogger(__name__)


class TakeH5:
    """An open take file (`file`) and the part files it links to, opened on first use.

    `get(hpath)` / `[hpath]` answer HDF5 paths as `h5py.File` does, resolving the links of a
    joined take explicitly; `close()` closes the parts too."""

    def __init__(self, path: str | Path, mode: str = "r", **kwargs: Any) -> None:
        self.path = Path(path)
        self.file = open_checked(self.path, mode, **kwargs)
        self._kwargs = kwargs
        try:
            self.manifest: list[PartEntry] | None = read_manifest(self.file, self.path)
        except BaseException:
            self.file.close()
            raise
        self._links = linked_files(self.manifest)
        self._parts: dict[str, h5py.File] = {}

    @property
    def attrs(self) -> h5py.AttributeManager:
        return self.file.attrs

    @property
    def joined(self) -> bool:
        """Whether the take is joined from the part files of a multi-host rig."""
        return self.manifest is not None

    def get(self, hpath: str) -> Any:
        """The group or dataset at `hpath` (None when there is none), through the part file
        where a link leads into one."""
        node: Any = self.file
        where = ""
        for name in hpath.strip("/").split("/"):
            if not name:
                continue
            if not isinstance(node, h5py.Group):
                return None
            link = node.get(name, getlink=True)
            where = f"{where}/{name}"
            if isinstance(link, h5py.ExternalLink):
                node = self._linked(where, link)
            elif isinstance(link, h5py.HardLink):
                node = node.get(name)
            else:  # absent; a soft link never passes the structure check
                return None
        return node

    def __getitem__(self, hpath: str) -> Any:
        node = self.get(hpath)
        if node is None:
            raise KeyError(f"{self.path}: /{hpath.strip('/')} does not exist")
        return node

    def __contains__(self, hpath: str) -> bool:
        return self.get(hpath) is not None

    def part_file(self, hpath: str) -> Path:
        """The file that holds the object at `hpath`: the take itself or one of its parts."""
        node = self.get(hpath)
        return self.path if node is None else Path(node.file.filename)

    def _linked(self, where: str, link: h5py.ExternalLink) -> Any:
        target = check_link(self.path, where, link, self._links)
        pf = self._parts.get(link.filename)
        if pf is None:
            pf = open_checked(target, "r", part=True, **self._kwargs)
            try:
                check_header(pf, target)
            except BaseException:
                pf.close()
                raise
            self._parts[link.filename] = pf
            log.debug("take %s: opened part %s for %s", self.path, target, where)
        node = pf.get(link.path)  # a part holds no link: this path stays inside it
        if node is None:
            raise TakeFormatError(f"{self.path}: {where}: links to {link.path!r} in {target}, which has none")
        return node

    def close(self) -> None:
        for pf in self._parts.values():
            pf.close()
        self._parts.clear()
        self.file.close()

    def __bool__(self) -> bool:
        return bool(self.file)

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def open_take_h5(path: str | Path, mode: str = "r", **kwargs: Any) -> TakeH5:
    """Open a take for reading its HDF5 objects directly (see `TakeH5`)."""
    return TakeH5(path, mode, **kwargs)
