"""The parts manifest of a multi-host take (root attr `parts_json`, docs/take-format.md
"Multi-host takes"): which host wrote which part file, which devices it holds, its checksum and
what state it was in when the take was joined.

The structure check reads it before it lets a single external link through: a joined take may
link only to the files its own manifest names, so the manifest is parsed strictly and small.
"""

from __future__ import annotations

import re
from typing import Literal

import h5py
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from rigd.core.errors import TakeFormatError
from rigd.core.layout import Root

#: A part file's name: a plain file name in the take's directory, `<stem>.<host>.part.h5`.
PART_NAME = r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,200}\.part\.h5$"
#: A host or device name (as in the rig config).
_NAME = r"^[A-Za-z][A-Za-z0-9_-]{0,63}$"
#: More hosts than any rig has; bounds what a hostile manifest makes the reader do.
MAX_PARTS = 64

PartStatus = Literal["complete", "missing", "unfinished", "failed", "damaged", "foreign"]


class PartEntry(BaseModel):
    """One host's part of a joined take."""

    model_config = ConfigDict(extra="forbid")

    host: str = Field(pattern=_NAME)
    file: str | None = Field(None, pattern=PART_NAME, description="Relative name; None: no file was there.")
    devices: list[str] = Field(description="The cameras and event sensors the host ran.")
    coordinator: bool = Field(False, description="This host owns the trigger box; /trigger is its.")
    sha256: str | None = Field(None, pattern=r"^[0-9a-f]{64}$")
    size: int | None = Field(None, ge=0)
    status: PartStatus = Field(
        description="complete: linked; missing: no file; unfinished/failed: not sealed (`rigd recover` "
        "on its host); damaged: breaks the take format; foreign: not a part of this take."
    )
    verdict: str | None = Field(None, description="The part's own verdict when it was read.")
    reason: str | None = Field(None, description="Why a part is not linked.")

    @property
    def linked(self) -> bool:
        return self.status == "complete"


_ENTRIES = TypeAdapter(list[PartEntry])


def dump_manifest(entries: list[PartEntry]) -> str:
    return _ENTRIES.dump_json(entries).decode()


def read_manifest(f: h5py.File, where: object) -> list[PartEntry] | None:
    """The manifest of an open take, None when it is not a joined take; TakeFormatError naming
    `where` when it is malformed."""
    raw = f.attrs.get(Root.PARTS)
    if raw is None:
        return None
    text = raw.decode("utf-8", "replace") if isinstance(raw, bytes) else raw
    if not isinstance(text, str):
        raise TakeFormatError(f"{where}: / attr {Root.PARTS} is not text")
    try:
        entries = _ENTRIES.validate_json(text)
    except ValidationError as exc:
        first = exc.errors()[0]
        loc = ".".join(str(x) for x in first["loc"])
        raise TakeFormatError(f"{where}: / attr {Root.PARTS}: {loc}: {first['msg']}") from None
    if len(entries) > MAX_PARTS:
        raise TakeFormatError(
            f"{where}: / attr {Root.PARTS} lists {len(entries)} parts (at most {MAX_PARTS})"
        )
    files = [e.file for e in entries if e.file is not None]
    if len(set(files)) != len(files):
        raise TakeFormatError(f"{where}: / attr {Root.PARTS} names a part file twice")
    for e in entries:
        for d in e.devices:
            if not re.fullmatch(_NAME, d):
                raise TakeFormatError(f"{where}: / attr {Root.PARTS}: host {e.host}: bad device name {d!r}")
    return entries


def linked_files(entries: list[PartEntry] | None) -> frozenset[str]:
    """The part files a joined take may link to: those of its linked parts."""
    return frozenset(e.file for e in entries or () if e.linked and e.file is not None)
