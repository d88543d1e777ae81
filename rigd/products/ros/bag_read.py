"""Reading a rosbag2 recording message by message: sqlite3 (`.db3`) or MCAP, a file or a bag
directory (its `metadata.yaml` beside the storage files), in log-time order, streaming.

Only the container is read here; the CDR payloads are deserialized by the caller with the
shipped definitions (rigd.products.ros.msgdefs), which is what lets a bag made anywhere be read.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from rigd.core.errors import RigdError
from rigd.core.extras import require

BAG_SUFFIXES = (".db3", ".mcap")


class BagError(RigdError):
    """A rosbag2 recording that cannot be read as one."""


@dataclass(frozen=True, slots=True)
class BagMessage:
    topic: str
    typename: str
    log_ns: int
    data: bytes
    encoding: str
    """The topic's serialization format (rigd reads `cdr`)."""


def is_bag(path: Path) -> bool:
    """A `.db3` / `.mcap` file, or a directory that holds one."""
    if path.is_dir():
        return bool(storage_files(path, quiet=True))
    return path.suffix.lower() in BAG_SUFFIXES


def storage_files(path: Path, *, quiet: bool = False) -> list[Path]:
    """The storage files of a bag (a file: itself; a directory: its .db3/.mcap files, in order)."""
    if not path.is_dir():
        return [path]
    files = sorted(p for p in path.iterdir() if p.suffix.lower() in BAG_SUFFIXES)
    if not files and not quiet:
        raise BagError(f"{path}: a directory without .db3 or .mcap files, not a rosbag2 bag")
    return files


def topics(path: Path) -> dict[str, tuple[str, str]]:
    """topic -> (type, serialization format) over every storage file."""
    out: dict[str, tuple[str, str]] = {}
    for f in storage_files(path):
        out.update(_mcap_topics(f) if f.suffix.lower() == ".mcap" else _db3_topics(f))
    return out


def messages(path: Path) -> Iterator[BagMessage]:
    """Every message of the bag, file by file, each file in log-time order."""
    for f in storage_files(path):
        yield from _mcap_messages(f) if f.suffix.lower() == ".mcap" else _db3_messages(f)


def first_of_type(path: Path, typename: str) -> BagMessage | None:
    """The first message of `typename` (None: the bag has none), read through the index."""
    for f in storage_files(path):
        if f.suffix.lower() == ".mcap":
            names = [t for t, (typ, _) in _mcap_topics(f).items() if typ == typename]
            if names:
                with f.open("rb") as fh:
                    reader = _mcap_reader(fh, f)
                    for schema, channel, msg in reader.iter_messages(topics=names):  # type: ignore[attr-defined]
                        return BagMessage(
                            channel.topic,
                            schema.name,
                            int(msg.log_time),
                            bytes(msg.data),
                            channel.message_encoding,
                        )
            continue
        con = _connect(f)
        try:
            row = con.execute(
                "SELECT t.name, t.serialization_format, m.timestamp, m.data FROM messages m "
                "JOIN topics t ON m.topic_id = t.id WHERE t.type = ? ORDER BY m.timestamp LIMIT 1",
                (typename,),
            ).fetchone()
        finally:
            con.close()
        if row is not None:
            return BagMessage(row[0], typename, int(row[2]), bytes(row[3]), row[1])
    return None


def _connect(f: Path) -> sqlite3.Connection:
    if not f.is_file():
        raise BagError(f"{f}: no such file")
    try:
        con = sqlite3.connect(f"file:{f}?mode=ro", uri=True)
        con.execute("SELECT id, name, type, serialization_format FROM topics LIMIT 1").fetchall()
    except sqlite3.DatabaseError as exc:
        raise BagError(f"{f}: not a rosbag2 sqlite3 file ({exc})") from exc
    return con


def _db3_topics(f: Path) -> dict[str, tuple[str, str]]:
    con = _connect(f)
    try:
        rows = con.execute("SELECT name, type, serialization_format FROM topics").fetchall()
    finally:
        con.close()
    return {name: (typ, fmt) for name, typ, fmt in rows}


def _db3_messages(f: Path) -> Iterator[BagMessage]:
    con = _connect(f)
    try:
        by_id = {
            i: (name, typ, fmt)
            for i, name, typ, fmt in con.execute("SELECT id, name, type, serialization_format FROM topics")
        }
        cur = con.execute("SELECT topic_id, timestamp, data FROM messages ORDER BY timestamp, id")
        for topic_id, ts, data in cur:
            if topic_id not in by_id:
                raise BagError(f"{f}: a message names topic id {topic_id}, which the bag does not define")
            name, typ, fmt = by_id[topic_id]
            yield BagMessage(name, typ, int(ts), bytes(data), fmt)
    except sqlite3.DatabaseError as exc:
        raise BagError(f"{f}: reading its messages failed ({exc})") from exc
    finally:
        con.close()


def _mcap_reader(fh: object, f: Path) -> object:
    reader_mod = require("mcap.reader", "reading MCAP bags")
    try:
        return reader_mod.make_reader(fh)
    except Exception as exc:
        raise BagError(f"{f}: not an MCAP file ({exc})") from exc


def _mcap_topics(f: Path) -> dict[str, tuple[str, str]]:
    with f.open("rb") as fh:
        reader = _mcap_reader(fh, f)
        summary = reader.get_summary()  # type: ignore[attr-defined]
        if summary is None:
            raise BagError(f"{f}: MCAP file without a summary (unfinished); run `mcap recover` on it")
        return {
            ch.topic: (
                summary.schemas[ch.schema_id].name if ch.schema_id in summary.schemas else "",
                ch.message_encoding,
            )
            for ch in summary.channels.values()
        }


def _mcap_messages(f: Path) -> Iterator[BagMessage]:
    with f.open("rb") as fh:
        reader = _mcap_reader(fh, f)
        for schema, channel, msg in reader.iter_messages(log_time_order=True):  # type: ignore[attr-defined]
            name = schema.name if schema is not None else ""
            yield BagMessage(
                channel.topic, name, int(msg.log_time), bytes(msg.data), channel.message_encoding
            )
