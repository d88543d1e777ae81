"""One unreadable file in a take directory stops nothing: `rigd recover DIR` seals the other
takes and names each problem in one line; the daemon starts, moves the file aside to
`take_dir/unreadable/` (kept, never deleted) and serves."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import h5py
import pytest
import typer
from typer.testing import CliRunner

from rigd.app.commands.recover import recover_command
from rigd.app.config import ServiceConfig, default_sim_rig
from rigd.app.testing.crash import BAD
from rigd.app.testing.crash import unfinished as _unfinished
from rigd.take.recover_dir import RecoveryProblem, move_aside, recover_dir, scan_dir


def _dir_with(tmp_path: Path, kinds: list[str]) -> tuple[Path, list[Path], list[Path]]:
    """A take dir: an unfinished take before and after the bad files (names sort around them)."""
    d = tmp_path / "takes"
    d.mkdir()
    good = [_unfinished(d / "a-good.h5", n=4), _unfinished(d / "z-good.h5", n=4)]
    bad = []
    for kind in kinds:
        p = d / f"m-{kind}.h5"
        BAD[kind](p)
        bad.append(p)
    with h5py.File(d / "m-not-a-take.h5", "w") as f:  # valid HDF5, not ours: skipped, no problem
        f["x"] = [1]
    return d, good, bad


def _app() -> typer.Typer:
    app = typer.Typer()
    app.command()(recover_command)
    return app


@pytest.mark.slow
@pytest.mark.parametrize("kind", sorted(BAD))
def test_recover_dir_seals_the_others_and_reports_each_bad_file(tmp_path: Path, kind: str) -> None:
    d, good, bad = _dir_with(tmp_path, [kind])
    results = recover_dir(d)
    problems = [r for r in results if isinstance(r, RecoveryProblem)]
    sealed = {r.path for r in results if not isinstance(r, RecoveryProblem) and r.sealed}
    assert [p.path for p in problems] == [str(bad[0])]
    assert problems[0].error
    assert sealed == {str(p) for p in good}
    assert bad[0].exists()  # reported, not moved (the command leaves files where they are)


@pytest.mark.slow
def test_every_bad_file_reported_once_the_rest_sealed(tmp_path: Path) -> None:
    """All kinds at once. A file whose header still reads (a truncated take) is listed as
    unfinished by the scan and reported when its recovery fails; the others at the scan."""
    d, good, bad = _dir_with(tmp_path, sorted(BAD))
    scan = scan_dir(d)
    unreadable = [Path(p.path) for p in scan.unreadable]
    assert set(good) <= set(scan.unfinished)
    assert sorted([*unreadable, *(set(scan.unfinished) - set(good))]) == sorted(bad)
    results = recover_dir(d)
    assert sorted(Path(r.path) for r in results if isinstance(r, RecoveryProblem)) == sorted(bad)
    assert {r.path for r in results if not isinstance(r, RecoveryProblem) and r.sealed} == {
        str(p) for p in good
    }


@pytest.mark.slow
def test_recover_command_dir_with_bad_files(tmp_path: Path) -> None:
    d, good, bad = _dir_with(tmp_path, sorted(BAD))
    res = CliRunner().invoke(_app(), [str(d)])
    assert res.exit_code == 1, res.output
    assert isinstance(res.exception, SystemExit), res.exception  # exit 1, nothing raised
    assert "Traceback" not in res.stdout
    lines = res.stdout.splitlines()  # the report of what was sealed
    errors = res.stderr.splitlines()  # one line per problem, naming the file, and nothing else on it
    for p in bad:
        assert sum(str(p) in line for line in errors) == 1, res.stderr
        assert not any(str(p) in line for line in lines), res.stdout
    for p in good:
        assert any(str(p) in line and "sealed complete" in line for line in lines), res.stdout


def test_recover_command_json_reports_the_problems(tmp_path: Path) -> None:
    d, good, bad = _dir_with(tmp_path, ["zero", "random"])
    res = CliRunner().invoke(_app(), ["--json", str(d)])
    assert res.exit_code == 1, res.output
    out: list[dict[str, Any]] = json.loads(res.stdout)
    assert {r["path"] for r in out if "error" in r} == {str(p) for p in bad}
    assert {r["path"] for r in out if r.get("outcome") == "sealed"} == {str(p) for p in good}


def test_recover_command_only_good_takes_exits_zero(tmp_path: Path) -> None:
    d, _, _ = _dir_with(tmp_path, [])
    res = CliRunner().invoke(_app(), [str(d)])
    assert res.exit_code == 0, res.output


def test_recover_command_bad_file_named_goes_on_with_the_next(tmp_path: Path) -> None:
    _, good, bad = _dir_with(tmp_path, ["text"])
    res = CliRunner().invoke(_app(), [str(bad[0]), str(good[0])])
    assert res.exit_code == 1, res.output
    assert "sealed complete" in res.output
    assert str(bad[0]) in res.output


def test_move_aside_keeps_files_and_never_overwrites(tmp_path: Path) -> None:
    d = tmp_path / "takes"
    d.mkdir()
    moved = []
    for i in range(3):
        p = d / "bad.h5"
        p.write_bytes(f"junk {i}".encode())
        moved.append(move_aside(p, d))
        assert not p.exists()
    assert [m.name for m in moved] == ["bad.h5", "bad.1.h5", "bad.2.h5"]
    assert [m.read_bytes() for m in moved] == [b"junk 0", b"junk 1", b"junk 2"]
    assert all(m.parent == d / "unreadable" for m in moved)


def test_move_aside_without_hard_links(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def no_links(src: Any, dst: Any) -> None:
        raise OSError(1, "Operation not permitted")

    d = tmp_path / "takes"
    (d / "unreadable").mkdir(parents=True)
    (d / "unreadable" / "bad.h5").write_bytes(b"earlier")
    (d / "bad.h5").write_bytes(b"now")
    monkeypatch.setattr(os, "link", no_links)
    dest = move_aside(d / "bad.h5", d)
    assert dest.name == "bad.1.h5"
    assert dest.read_bytes() == b"now"
    assert (d / "unreadable" / "bad.h5").read_bytes() == b"earlier"


def test_recover_dir_move_unreadable(tmp_path: Path) -> None:
    d, _, bad = _dir_with(tmp_path, ["zero", "random", "truncated"])
    results = recover_dir(d, move_unreadable=True)
    problems = [r for r in results if isinstance(r, RecoveryProblem)]
    assert sorted(Path(p.moved_to or "").name for p in problems) == sorted(p.name for p in bad)
    assert not any(p.exists() for p in bad)
    assert {p.name for p in (d / "unreadable").iterdir()} == {p.name for p in bad}
    # A second pass finds nothing left to trip over.
    assert recover_dir(d, move_unreadable=True) == []


def test_recover_dir_dry_run_moves_nothing(tmp_path: Path) -> None:
    d, _, bad = _dir_with(tmp_path, ["zero"])
    results = recover_dir(d, dry_run=True, move_unreadable=True)
    assert any(isinstance(r, RecoveryProblem) for r in results)
    assert bad[0].exists()


def test_recover_command_removes_the_ballast_a_killed_capture_left(tmp_path: Path) -> None:
    d, _, _ = _dir_with(tmp_path, [])
    stale = d / ".rigd-ballast-12345678-0123abcd"  # no process 12345678: pid_max is 4194304
    stale.write_bytes(b"\0" * 1024)
    res = CliRunner().invoke(_app(), [str(d)])
    assert res.exit_code == 0, res.output
    assert not stale.exists()


def test_recover_with_no_path_searches_the_configs_take_dir(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`rigd recover` as the README writes it: no path means the rig config's take_dir."""
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(_app(), [])
    assert res.exit_code == 0, res.output
    assert "no take directory takes: nothing to recover" in res.stderr
    d, good, _ = _dir_with(tmp_path, [])
    config = tmp_path / "rig.json"
    config.write_text(
        default_sim_rig().model_copy(update={"service": ServiceConfig(take_dir=d)}).model_dump_json()
    )
    res = CliRunner().invoke(_app(), ["--config", str(config)])
    assert res.exit_code == 0, res.output
    assert f"searching {d}" in " ".join(res.stderr.split())
    for p in good:
        assert any(str(p) in line and "sealed complete" in line for line in res.stdout.splitlines())


@pytest.mark.slow
def test_recover_says_each_problem_once(tmp_path: Path) -> None:
    """Through the real command line (its logging set up): a bad file is one report line,
    not a log line and then the same again."""
    from rigd.app.cli import app

    d, _, bad = _dir_with(tmp_path, ["text", "zero"])
    res = CliRunner().invoke(app, ["recover", str(d)])
    assert res.exit_code == 1, res.output
    for p in bad:
        assert res.output.count(p.name) == 1, res.output
