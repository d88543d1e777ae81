"""Unreadable files in take_dir do not keep the daemon from starting (no restart loop under
systemd): each is reported, moved to take_dir/unreadable/ (kept), and the daemon serves."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from rigd.app.service.client import DaemonClient
from rigd.app.testing.crash import BAD
from rigd.app.testing.crash import unfinished as _unfinished
from rigd.app.testing.daemon import endpoints, small_rig, spawn_daemon


def _populate(take_dir: Path) -> tuple[Path, list[Path]]:
    take_dir.mkdir(parents=True)
    good = _unfinished(take_dir / "a-good.h5", n=4)
    bad = []
    for kind, make in sorted(BAD.items()):
        p = take_dir / f"m-{kind}.h5"
        make(p)
        bad.append(p)
    (take_dir / "unreadable").mkdir()
    (take_dir / "unreadable" / "m-zero.h5").write_bytes(b"moved aside by an earlier start")
    return good, bad


def test_daemon_starts_with_unreadable_takes_and_moves_them_aside(tmp_path: Path, start_daemon: Any) -> None:
    take_dir = tmp_path / "takes"
    good, bad = _populate(take_dir)
    rd = start_daemon()
    assert rd.client.call("ping")["state"] == "idle"
    by_path = {r["path"]: r for r in rd.daemon.recovered}
    assert by_path[str(good)]["outcome"] == "sealed"
    for p in bad:
        problem = by_path[str(p)]
        assert problem["error"], problem
        assert problem["moved_to"], problem
        assert Path(problem["moved_to"]).parent == take_dir / "unreadable"
        assert Path(problem["moved_to"]).is_file()
        assert not p.exists()
    # The file an earlier start moved aside is kept; the new one got another name.
    assert (take_dir / "unreadable" / "m-zero.h5").read_bytes() == b"moved aside by an earlier start"
    assert Path(by_path[str(take_dir / "m-zero.h5")]["moved_to"]).name == "m-zero.1.h5"
    # A capture still works after such a start.
    assert rd.client.call("config")["service"]["take_dir"] == str(take_dir)


def test_recover_command_reports_unreadable_files(tmp_path: Path, start_daemon: Any) -> None:
    rd = start_daemon()
    take_dir = Path(rd.config.service.take_dir)
    junk = take_dir / "late-junk.h5"
    junk.write_bytes(b"\x00" * 100)
    res = rd.client.call("recover", timeout_s=60)
    [problem] = res["recovered"]
    assert problem["path"] == str(junk)
    assert problem["moved_to"] == str(take_dir / "unreadable" / "late-junk.h5")
    assert rd.client.call("ping")["state"] == "idle"


@pytest.mark.slow
def test_rigd_serve_process_starts_with_unreadable_takes(runtime_dir: Path, tmp_path: Path) -> None:
    """`rigd serve` as systemd runs it: it must answer, not exit at start."""
    take_dir = tmp_path / "takes"
    _, bad = _populate(take_dir)
    cfg = small_rig("unreadable", take_dir=str(take_dir))
    proc = spawn_daemon(cfg, runtime_dir, tmp_path / "daemon.log")  # asserts it answers a ping
    try:
        with DaemonClient(endpoints(runtime_dir)["control"], timeout_s=10) as client:
            assert client.call("ping")["state"] == "idle"
    finally:
        proc.terminate()
        proc.wait(timeout=60)
    assert proc.returncode == 0, (tmp_path / "daemon.log").read_text()[-3000:]
    log = (tmp_path / "daemon.log").read_text()
    for p in bad:
        assert str(p) in log
        assert not p.exists()
