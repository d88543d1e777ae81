"""The `% key value` header of a Prophesee RAW file: parsing (format, geometry, every field kept)
and writing. Apart from the stream decoder (`raw`) so DAT files and tools read headers alone."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import BinaryIO

from rigd.core.errors import EventDataError

log = logging.getLogger(__name__)

_FORMAT_NAMES = {"EVT3": "evt3", "EVT2": "evt2", "EVT21": "evt21"}
_EVT_VERSIONS = {"3.0": "evt3", "2.0": "evt2", "2.1": "evt21"}
# (plugin / sensor name fragment, width, height) for old headers without geometry
_SENSOR_GEOMETRY = (
    ("gen3", 640, 480),
    ("gen4", 1280, 720),
    ("imx636", 1280, 720),
    ("imx646", 1280, 720),
    ("genx320", 320, 320),
    ("imx8", 320, 320),
)


@dataclass(slots=True)
class RawHeader:
    """Parsed `% key value` header of a RAW file; `fields` keeps every line's key and value."""

    fmt: str = "evt3"
    width: int = 1280
    height: int = 720
    fields: dict[str, str] = field(default_factory=dict)
    size: int = 0  # header bytes in the file (where the event stream starts)

    @property
    def serial_number(self) -> str | None:
        return self.fields.get("serial_number")

    def to_bytes(self) -> bytes:
        """New-style header (with `% evt` kept for old readers), ending in `% end`."""
        name = {"evt3": "EVT3", "evt2": "EVT2", "evt21": "EVT21", "evt21_le": "EVT21"}[self.fmt]
        version = {"evt3": "3.0", "evt2": "2.0", "evt21": "2.1", "evt21_le": "2.1"}[self.fmt]
        fmt_line = f"{name};height={self.height};width={self.width}"
        if self.fmt == "evt21_le":
            fmt_line += ";endianness=little"
        elif self.fmt == "evt21":  # IMX636's half-swapped words: the header OpenEB writes for them
            fmt_line += ";endianness=legacy"
        lines = [f"% evt {version}", f"% format {fmt_line}", f"% geometry {self.width}x{self.height}"]
        skip = {"evt", "format", "geometry", "end"}
        lines += [f"% {k} {v}".rstrip() for k, v in self.fields.items() if k not in skip]
        lines.append("% end")
        return ("\n".join(lines) + "\n").encode("ascii")


def read_header_lines(f: BinaryIO) -> tuple[list[str], int]:
    lines: list[str] = []
    while True:
        start = f.tell()
        if f.read(1) != b"%":
            f.seek(start)
            break
        raw = b"%" + f.readline()
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError:
            f.seek(start)  # a binary word that happens to start with '%'
            break
        if not text.endswith("\n") or any(not (c.isprintable() or c in "\r\n\t") for c in text):
            f.seek(start)
            break
        text = text.rstrip("\r\n")
        lines.append(text)
        if text.strip() == "% end":
            break
    return lines, f.tell()


def _header_int(where: str, key: str, value: str) -> int:
    """A header number, or an EventDataError naming the file and the line's key."""
    try:
        return int(value)
    except ValueError:
        raise EventDataError(f"{where}: RAW header {key} {value!r} is not an integer") from None


def parse_raw_header(f: BinaryIO) -> RawHeader:
    """Read the header at the current position; leaves `f` at the first stream byte. A number
    that is not one (`width=abc`) is an EventDataError naming the file."""
    where = str(getattr(f, "name", "RAW stream"))
    lines, size = read_header_lines(f)
    fields: dict[str, str] = {}
    for line in lines:
        body = line[1:].strip()
        if not body:
            continue
        key, _, value = body.partition(" ")
        fields[key] = value.strip()
    hdr = RawHeader(fields=fields, size=size)
    width = height = None
    fmt = None
    if "format" in fields:
        parts = fields["format"].split(";")
        fmt = _FORMAT_NAMES.get(parts[0].strip().upper())
        params = dict(p.split("=", 1) for p in parts[1:] if "=" in p)
        if fmt == "evt21" and params.get("endianness", "").lower() == "little":
            fmt = "evt21_le"
        given = {k: _header_int(where, f"format {k}", params[k]) for k in ("width", "height") if k in params}
        if len(given) == 2:
            width, height = given["width"], given["height"]
    if fmt is None and "evt" in fields:
        fmt = _EVT_VERSIONS.get(fields["evt"])
    if width is None and "geometry" in fields and "x" in fields["geometry"]:
        gw, _, gh = fields["geometry"].partition("x")
        width, height = _header_int(where, "geometry", gw), _header_int(where, "geometry", gh)
    if width is None:
        sensor = " ".join(
            fields.get(k, "") for k in ("plugin_name", "sensor_generation", "system_ID")
        ).lower()
        for frag, w, h in _SENSOR_GEOMETRY:
            if frag in sensor:
                width, height = w, h
                break
    if fmt is None:
        if fields:  # no header at all is the caller's to judge (RawReader refuses it)
            log.warning("RAW header names no known format (%s); assuming EVT 3.0", fields.get("format"))
        fmt = "evt3"
    hdr.fmt = fmt
    if width is not None and height is not None:
        hdr.width, hdr.height = width, height
    return hdr
