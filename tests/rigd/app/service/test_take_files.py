"""take_read / take_stat on a daemon's control socket, and `rigd takes gather` fetching a
multi-host take's part through them (resumably, checked by sha256) before joining it again."""

from __future__ import annotations

import base64
import json
import os
import shutil
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from firmware_sim.testing.takes import make_take
from rigd.app.cli import app
from rigd.app.config import HostConfig
from rigd.app.service.client import DaemonClient, DaemonRequestError
from rigd.app.service.daemon import Daemon
from rigd.app.service.protocol import ErrorInfo
from rigd.app.take_gather import gather_take
from rigd.app.testing.daemon import endpoints, serve_in_thread, small_rig
from rigd.core.errors import TakeError
from rigd.take import Take
from rigd.take.parts import file_sha256, join_take, part_name
from tests.rigd.take.test_parts import STEM, make_parts

B = part_name(STEM, "B")


@pytest.fixture
def host_b(tmp_path: Path) -> Iterator[tuple[DaemonClient, Path, str]]:
    """A daemon whose take directory holds host B's part; its client, take dir and endpoint."""
    runtime = tmp_path / "run-b"
    runtime.mkdir(mode=0o700)
    take_dir = tmp_path / "host-b"
    take_dir.mkdir()
    ep = endpoints(runtime)
    cfg = small_rig(
        f"files-{uuid.uuid4().hex[:6]}",
        take_dir=str(take_dir),
        control=ep["control"],
        telemetry=ep["telemetry"],
    )
    daemon = Daemon(cfg, metrics=False)
    thread, errors = serve_in_thread(daemon, "daemon-b")
    client = DaemonClient(ep["control"], timeout_s=10)
    try:
        yield client, take_dir, ep["control"]
    finally:
        client.close()
        daemon.shutdown()
        thread.join(30)
    assert not errors


@pytest.fixture
def split(tmp_path: Path) -> tuple[Path, Path]:
    """A joined take on the coordinator whose part B is only on host B (degraded here)."""
    whole = make_take(tmp_path / "whole.h5").path
    coord = tmp_path / "coord"
    refs = make_parts(whole, coord)
    b_dir = tmp_path / "host-b"
    b_dir.mkdir(exist_ok=True)
    shutil.move(coord / B, b_dir / B)
    joined = coord / f"{STEM}.h5"
    res = join_take(joined, refs[0].file or Path(), refs, missing={"B": "host B died"})
    assert res.missing_devices == ["ev0"]
    return joined, b_dir / B


def _stat(client: DaemonClient, name: str) -> dict[str, object]:
    deadline = time.monotonic() + 60
    while (st := client.call("take_stat", file=name))["sha256"] is None:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    return st


def test_take_read_and_stat_serve_the_take_dirs_files(
    host_b: tuple[DaemonClient, Path, str], split: tuple[Path, Path]
) -> None:
    client, _, _ = host_b
    part = split[1]
    data = part.read_bytes()
    got = client.call("take_read", file=B, offset=100, length=5000)
    assert got["size"] == len(data)
    assert base64.b64decode(got["data_b64"]) == data[100:5100]
    tail = client.call("take_read", file=B, offset=len(data) - 10, length=4096)
    assert base64.b64decode(tail["data_b64"]) == data[-10:]
    st = _stat(client, B)
    assert (st["sha256"], st["size"]) == (file_sha256(part), len(data))
    # binary: the bytes as the reply's second frame, `length` saying how many
    res, payload = client.call_with_payload("take_read", file=B, offset=100, length=5000, binary=True)
    assert (res["length"], res["size"], payload) == (5000, len(data), data[100:5100])
    assert "data_b64" not in res
    res, payload = client.call_with_payload("take_read", file=B, offset=len(data) + 5, length=10, binary=True)
    assert (res["length"], payload) == (0, b"")
    # the base64 form has no second frame; an error has none either
    assert client.call_with_payload("take_read", file=B, offset=0, length=10)[1] is None
    with pytest.raises(DaemonRequestError, match="no take file"):
        client.call_with_payload("take_read", file="gone.h5", offset=0, length=10, binary=True)
    assert client.call("ping") is not None  # the socket is in step after the error


class _OldDaemon:
    """A host whose daemon predates binary take_read: it refuses the argument."""

    def __init__(self, data: bytes) -> None:
        self.data = data

    def call_with_payload(self, cmd: str, **args: object) -> tuple[dict[str, object], bytes | None]:
        raise DaemonRequestError(ErrorInfo(code="bad_request", message="extra field", field="args.binary"))

    def call(self, cmd: str, *, file: str, offset: int, length: int) -> dict[str, str]:
        return {"data_b64": base64.b64encode(self.data[offset : offset + length]).decode()}


def test_a_daemon_without_binary_reads_is_read_through_base64() -> None:
    from rigd.app.take_gather import read_block

    data = bytes(range(256)) * 4
    assert read_block(_OldDaemon(data), "p.part.h5", 10, 100) == data[10:110]  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("name", "code"),
    [
        ("../x.h5", "bad_request"),
        ("/etc/passwd", "bad_request"),
        (".hidden.h5", "bad_request"),
        ("a/b.h5", "bad_request"),
    ],
)
def test_take_read_refuses_anything_but_a_take_name(
    host_b: tuple[DaemonClient, Path, str], name: str, code: str
) -> None:
    client, _, _ = host_b
    with pytest.raises(DaemonRequestError, match=code):
        client.call("take_read", file=name, offset=0, length=10)
    with pytest.raises(DaemonRequestError, match=code):
        client.call("take_stat", file=name)


def test_take_read_refuses_links_fifos_and_big_reads(
    host_b: tuple[DaemonClient, Path, str], tmp_path: Path
) -> None:
    client, take_dir, _ = host_b
    secret = tmp_path / "secret.h5"
    secret.write_bytes(b"private")
    (take_dir / "link.h5").symlink_to(secret)
    os.mkfifo(take_dir / "pipe.h5")
    with pytest.raises(DaemonRequestError, match=r"take_error: link\.h5: cannot be read"):
        client.call("take_read", file="link.h5", offset=0, length=10)
    with pytest.raises(DaemonRequestError, match=r"take_error: pipe\.h5: is not a regular file"):
        client.call("take_stat", file="pipe.h5")
    with pytest.raises(DaemonRequestError, match=r"take_error: no take file gone\.h5"):
        client.call("take_read", file="gone.h5", offset=0, length=10)
    with pytest.raises(DaemonRequestError, match=r"bad_request \(args.length\)"):
        client.call("take_read", file="link.h5", offset=0, length=(4 << 20) + 1)


def test_gather_fetches_a_missing_part_and_completes_the_take(
    host_b: tuple[DaemonClient, Path, str], split: tuple[Path, Path]
) -> None:
    _, _, ep = host_b
    joined, remote = split
    res = gather_take(joined, {"B": HostConfig(control=ep)})
    assert res.actions["A"].startswith("kept")
    assert res.actions["B"] == f"copied {remote.stat().st_size:,} bytes"
    assert res.join is not None
    assert res.join.verdict.verdict == "complete"
    assert (joined.parent / B).read_bytes() == remote.read_bytes()
    with Take(joined) as t:
        assert t.sensor("ev0").count == 20_000
    assert gather_take(joined, {"B": HostConfig(control=ep)}).actions["B"] == "up to date"


def test_gather_resumes_a_partial_copy_and_restarts_a_wrong_one(
    host_b: tuple[DaemonClient, Path, str], split: tuple[Path, Path]
) -> None:
    _, _, ep = host_b
    joined, remote = split
    data = remote.read_bytes()
    partial = joined.parent / f"{B}.partial"
    meta = joined.parent / f"{B}.partial.json"
    meta.write_text(json.dumps({"sha256": file_sha256(remote), "size": len(data)}))
    partial.write_bytes(data[:300_000])
    res = gather_take(joined, {"B": HostConfig(control=ep)})
    assert res.actions["B"] == f"copied {len(data):,} bytes, resumed at byte 300,000"
    assert (joined.parent / B).read_bytes() == data
    assert not partial.exists()
    assert not meta.exists()
    (joined.parent / B).unlink()
    meta.write_text(json.dumps({"sha256": file_sha256(remote), "size": len(data)}))
    partial.write_bytes(data[:1000] + b"\0" * 1000)  # not the host's bytes: copied again from 0
    res = gather_take(joined, {"B": HostConfig(control=ep)})
    assert res.actions["B"] == f"copied {len(data):,} bytes"
    assert res.join is not None
    assert res.join.verdict.verdict == "complete"


def test_gather_cli_says_what_it_did_and_exits_1_while_a_host_is_unreachable(
    split: tuple[Path, Path], tmp_path: Path
) -> None:
    joined, _ = split
    cfg = small_rig("gather-cli").model_dump(mode="json")
    cfg["hosts"] = {"B": {"control": f"ipc://{tmp_path}/nobody.sock"}}
    for dev in cfg["cameras"]:
        dev["host"] = "B"
    for dev in cfg["event_sensors"]:
        dev["host"] = "B"
    cfg["trigger"]["host"] = "B"
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(cfg))
    r = CliRunner().invoke(app, ["takes", "gather", str(joined), "--config", str(path), "--timeout", "0.5"])
    assert r.exit_code == 1, r.output
    assert "B: not gathered from ipc://" in r.stdout
    assert "degraded" in r.stdout


def test_gather_cli_refuses_a_take_that_is_not_joined(tmp_path: Path) -> None:
    plain = make_take(tmp_path / "plain.h5").path
    r = CliRunner().invoke(app, ["takes", "gather", str(plain)])
    assert r.exit_code == 2, r.output
    assert "is not a multi-host take (no parts manifest)" in r.stderr


def test_gather_cli_json_reports_each_host_and_the_verdict(
    host_b: tuple[DaemonClient, Path, str], split: tuple[Path, Path], tmp_path: Path
) -> None:
    _, _, ep = host_b
    joined, _ = split
    cfg = small_rig("gather-json").model_dump(mode="json")
    cfg["hosts"] = {"A": {"control": f"ipc://{tmp_path}/a.sock"}, "B": {"control": ep}}
    cfg["trigger"]["host"] = "A"
    for dev in [*cfg["cameras"], *cfg["event_sensors"]]:
        dev["host"] = "B"
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(cfg))
    r = CliRunner().invoke(
        app, ["takes", "gather", str(joined), "--config", str(path), "--json", "--timeout", "0.5"]
    )
    assert r.exit_code == 0, r.output
    body = json.loads(r.stdout)
    assert body["actions"]["A"].startswith("not gathered from ipc://")  # its file is here: kept
    assert body["actions"]["B"].startswith("copied ")
    assert body["verdict"]["verdict"] == "complete"
    assert [p["status"] for p in body["parts"]] == ["complete", "complete"]


class _FakeHost:
    """take_read answers from bytes; `short_at` cuts the file there (it shrank on the host)."""

    def __init__(self, data: bytes, short_at: int | None = None) -> None:
        self.data = data if short_at is None else data[:short_at]
        self.calls: list[int] = []

    def call_with_payload(
        self, cmd: str, *, file: str, offset: int, length: int, binary: bool
    ) -> tuple[dict[str, int], bytes]:
        assert (cmd, binary) == ("take_read", True)
        self.calls.append(offset)
        got = self.data[offset : offset + length]
        return {"length": len(got)}, got


def test_overlapping_reads_come_back_in_order_and_a_short_file_is_named(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from rigd.app import take_gather

    monkeypatch.setattr(take_gather, "BLOCK", 1000)
    data = bytes(range(256)) * 40  # 10,240 bytes: 11 blocks, the last short
    hosts = [_FakeHost(data) for _ in range(3)]
    got = b"".join(take_gather._read_blocks(hosts, "p.part.h5", 2000, len(data)))  # type: ignore[arg-type]
    assert got == data[2000:]
    assert sorted(o for h in hosts for o in h.calls) == list(range(2000, len(data), 1000))
    shrunk = [_FakeHost(data, short_at=5500) for _ in range(3)]
    with pytest.raises(TakeError, match=r"p\.part\.h5: the host's file ended at byte 5500 of 10240"):
        b"".join(take_gather._read_blocks(shrunk, "p.part.h5", 0, len(data)))  # type: ignore[arg-type]
