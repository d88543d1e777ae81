"""`rigd takes gather`: copy a multi-host take's parts from their hosts, then join it again.

The coordinator joins a take from the parts beside it; a part that was missing (its host died
mid-take and ran `rigd recover` since) or whose checksum differs from its host's copy is
fetched through that host's daemon (`take_stat`, `take_read`: rigd/app/service/take_files.py)
into `<part>.partial`, resumably: a partial left by an interrupted gather is continued from its
size when the host's file is the one it was copying (sha256 and size in `<part>.partial.json`)
and its last block matches the host's bytes, and started again otherwise. The copy is renamed
into place only once its sha256 is the host's; then the take is joined again (`join_take`).
"""

from __future__ import annotations

import base64
import functools
import json
import logging
import os
import queue
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py

from rigd.app.config import HostConfig
from rigd.app.service.client import DaemonClient, DaemonRequestError, DaemonUnavailableError
from rigd.core.errors import ConfigError, RigdError, TakeError
from rigd.core.layout import Root
from rigd.take.manifest import PartEntry, read_manifest
from rigd.take.parts import JoinResult, PartRef, file_sha256, join_take, part_name
from rigd.take.structure import check_regular_file

log = logging.getLogger(__name__)

#: Bytes asked for per `take_read` (the protocol's most).
BLOCK = 4 << 20
#: `take_read` requests in flight per part (one client each): while one block crosses the
#: network and is decoded, the host reads and encodes the next.
READS_IN_FLIGHT = 3
#: How long a host may take to checksum its part (a few GB at disk speed).
HASH_WAIT_S = 900.0

ClientFactory = Callable[[HostConfig, float], DaemonClient]


@dataclass(slots=True)
class GatherResult:
    """What gathering did per host, and the take joined again."""

    actions: dict[str, str] = field(default_factory=dict)
    join: JoinResult | None = None


def default_client(host: HostConfig, timeout_s: float) -> DaemonClient:
    return DaemonClient(
        host.control,
        timeout_s=timeout_s,
        server_public_key=host.server_public_key,
        client_secret_key=host.client_secret_key,
    )


def read_parts(joined: Path) -> list[PartEntry]:
    """The parts manifest of a joined take (its root attributes only: a part may be gone)."""
    check_regular_file(joined)
    try:
        with h5py.File(joined, "r") as f:
            entries = read_manifest(f, joined)
    except OSError as exc:
        raise TakeError(f"{joined}: cannot be opened as an HDF5 file: {exc}") from exc
    if entries is None:
        raise TakeError(f"{joined}: is not a multi-host take (no parts manifest)")
    return entries


def hosts_of_take(joined: Path) -> dict[str, HostConfig]:
    """The `hosts` table of the rig config the joined take stores (the coordinator's)."""
    check_regular_file(joined)
    try:
        with h5py.File(joined, "r") as f:
            raw = f.get(Root.CONFIG)
            text = raw[()] if isinstance(raw, h5py.Dataset) else b"{}"
        data = json.loads(text.decode() if isinstance(text, bytes) else text)
        hosts = (data.get("hosts") if isinstance(data, dict) else None) or {}
        return {name: HostConfig.model_validate(h) for name, h in hosts.items()}
    except (OSError, ValueError, TypeError, AttributeError) as exc:  # ValidationError is a ValueError
        raise ConfigError(
            f"{joined}: the rig config it stores gives no usable `hosts` ({exc}); pass --config"
        ) from exc


def gather_take(
    joined: Path,
    hosts: Mapping[str, HostConfig],
    *,
    timeout_s: float = 30.0,
    client: ClientFactory = default_client,
) -> GatherResult:
    """Fetch every part of `joined` that is missing here or differs from its host's, then join
    the take again. A host that cannot give its part is reported, and its devices stay out.
    `timeout_s`: how long each request to a host may wait for its answer."""
    entries = read_parts(joined)
    result = GatherResult()
    missing: dict[str, str] = {}
    fetches: dict[str, tuple[HostConfig, Path, Future[str]]] = {}
    with ThreadPoolExecutor(max(1, len(entries)), thread_name_prefix="gather") as pool:
        for entry in entries:  # every host's part at once: each comes from its own host's disk
            name = entry.file or part_name(joined.stem, entry.host)
            local = joined.parent / name
            cfg = hosts.get(entry.host)
            if cfg is None:
                if entry.coordinator or local.exists():
                    result.actions[entry.host] = "kept (no endpoint for this host in the rig config)"
                else:
                    missing[entry.host] = result.actions[entry.host] = (
                        "no endpoint for this host in the rig config"
                    )
                continue
            more = functools.partial(client, cfg, timeout_s)
            fetches[entry.host] = (cfg, local, pool.submit(fetch_part, more(), local, more))
        for host, (cfg, local, fut) in fetches.items():
            try:
                result.actions[host] = fut.result()
            except (RigdError, OSError) as exc:
                why = f"not gathered from {cfg.control}: {exc}"
                result.actions[host] = why
                if not local.exists():
                    missing[host] = why
    coordinator = next((e for e in entries if e.coordinator), None)
    if coordinator is None:
        raise TakeError(f"{joined}: its parts manifest names no coordinator")
    refs = []
    for e in entries:
        name = e.file or part_name(joined.stem, e.host)
        refs.append(
            PartRef(e.host, Path(name) if (joined.parent / name).exists() else None, tuple(e.devices))
        )
    coord_file = coordinator.file or part_name(joined.stem, coordinator.host)
    result.join = join_take(joined, Path(coord_file), refs, missing=missing)
    return result


def _stat(c: DaemonClient, name: str) -> dict[str, Any]:
    deadline = time.monotonic() + HASH_WAIT_S
    while True:
        st = c.call("take_stat", file=name)
        if st.get("sha256"):
            return st
        if time.monotonic() > deadline:
            raise TakeError(f"{name}: its host did not finish its checksum within {HASH_WAIT_S:g} s")
        time.sleep(0.2)


def fetch_part(c: DaemonClient, local: Path, more: Callable[[], DaemonClient] | None = None) -> str:
    """Make `local` the host's copy of its name; says what it did. `more` makes further clients
    of the same host, so READS_IN_FLIGHT reads overlap (None: one read at a time, through `c`)."""
    with c:
        try:
            st = _stat(c, local.name)
        except DaemonRequestError as exc:
            raise TakeError(f"the host answered: {exc}") from exc
        except DaemonUnavailableError as exc:
            raise TakeError(str(exc)) from exc
        sha, size = str(st["sha256"]), int(st["size"])
        if local.exists() and local.stat().st_size == size and file_sha256(local) == sha:
            return "up to date"
        partial = local.with_name(local.name + ".partial")
        meta = local.with_name(local.name + ".partial.json")
        start = _resume_from(c, partial, meta, sha, size)
        meta.write_text(json.dumps({"sha256": sha, "size": size}))
        with partial.open("r+b" if start else "wb") as f:
            f.truncate(start)
            f.seek(start)
            clients = [c] + ([more() for _ in range(READS_IN_FLIGHT - 1)] if more is not None else [])
            try:
                for data in _read_blocks(clients, local.name, start, size):
                    f.write(data)
            finally:
                for extra in clients[1:]:
                    extra.close()
            f.flush()
            os.fsync(f.fileno())
        got = file_sha256(partial)
        if got != sha:
            partial.unlink()
            meta.unlink(missing_ok=True)
            raise TakeError(f"{local.name}: the copy's sha256 {got} is not the host's {sha}; copy removed")
        os.replace(partial, local)
        meta.unlink(missing_ok=True)
        resumed = f", resumed at byte {start:,}" if start else ""
        log.info("gathered %s (%d bytes%s)", local, size, resumed)
        return f"copied {size:,} bytes{resumed}"


def read_block(c: DaemonClient, name: str, offset: int, length: int) -> bytes:
    """One `take_read`: the bytes as the reply's second frame, or base64 in its JSON from a
    daemon that predates binary replies (it refuses the `binary` argument)."""
    try:
        result, payload = c.call_with_payload(
            "take_read", file=name, offset=offset, length=length, binary=True
        )
    except DaemonRequestError as exc:
        if exc.error.field != "args.binary":
            raise
        return base64.b64decode(c.call("take_read", file=name, offset=offset, length=length)["data_b64"])
    if payload is None or len(payload) != result.get("length"):
        got = "no" if payload is None else f"{len(payload)}"
        raise TakeError(
            f"{name}: the host's reply at byte {offset} carried {got} bytes, not {result.get('length')}"
        )
    return payload


def _read_blocks(clients: list[DaemonClient], name: str, start: int, size: int) -> Iterator[bytes]:
    """The host's bytes of `name` from `start` to `size`, in order, block by block, with one
    request in flight per client (a REQ socket carries one at a time)."""
    free: queue.SimpleQueue[DaemonClient] = queue.SimpleQueue()
    for cl in clients:
        free.put(cl)

    def read(offset: int, length: int) -> bytes:
        cl = free.get()
        try:
            return read_block(cl, name, offset, length)
        finally:
            free.put(cl)

    with ThreadPoolExecutor(len(clients), thread_name_prefix="take_read") as pool:
        pending: deque[tuple[int, int, Future[bytes]]] = deque()
        offset = start
        try:
            while offset < size or pending:
                while offset < size and len(pending) < len(clients):
                    length = min(BLOCK, size - offset)
                    pending.append((offset, length, pool.submit(read, offset, length)))
                    offset += length
                at, length, fut = pending.popleft()
                data = fut.result()
                if len(data) != length:
                    raise TakeError(f"{name}: the host's file ended at byte {at + len(data)} of {size}")
                yield data
        finally:
            for _, _, fut in pending:
                fut.cancel()


def _resume_from(c: DaemonClient, partial: Path, meta: Path, sha: str, size: int) -> int:
    """Where to continue an interrupted copy: its size when it was copying this very file and
    its last block is the host's, else 0."""
    if not partial.exists() or not meta.exists():
        return 0
    try:
        was = json.loads(meta.read_text())
    except (OSError, json.JSONDecodeError):
        return 0
    have = partial.stat().st_size
    if was != {"sha256": sha, "size": size} or have > size or have == 0:
        log.info("%s: the host's file changed since the partial copy; starting again", partial)
        return 0
    tail = min(BLOCK, have)
    theirs = read_block(c, partial.name.removesuffix(".partial"), have - tail, tail)
    with partial.open("rb") as f:
        f.seek(have - tail)
        mine = f.read(tail)
    if mine != theirs:
        log.warning("%s: its last block differs from the host's; starting again", partial)
        return 0
    return have
