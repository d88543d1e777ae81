"""`rigd takes DIR`: every take in the directory with its verdict, length, devices and size; a file
that is not a readable take is a row saying why, not the end of the listing."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from firmware_sim.testing.takes import make_take
from rigd.app.cli import app

runner = CliRunner()


@pytest.mark.slow
def test_lists_each_take_with_verdict_devices_and_size(tmp_path: Path) -> None:
    make_take(tmp_path / "a.h5")
    make_take(tmp_path / "b.h5", finalize=False)
    (tmp_path / "junk.h5").write_bytes(b"not hdf5")
    (tmp_path / "notes.txt").write_text("not a take")
    r = runner.invoke(app, ["takes", str(tmp_path), "--json"])
    assert r.exit_code == 0, r.output
    rows = {row["name"]: row for row in json.loads(r.stdout)}
    assert set(rows) == {"a", "b", "junk"}
    a = rows["a"]
    assert a["status"] == "complete"
    assert a["error"] is None
    assert a["cameras"] == ["cam0"]
    assert a["event_sensors"] == ["ev0"]
    assert a["size_bytes"] == (tmp_path / "a.h5").stat().st_size
    assert a["duration_s"] is not None
    assert a["duration_s"] > 0
    assert rows["b"]["verdict"] == "unfinished"
    assert "recover" in rows["b"]["reason"]
    assert rows["junk"]["error"]

    table = runner.invoke(app, ["takes", str(tmp_path)])
    assert table.exit_code == 0, table.output
    lines = table.stdout.splitlines()
    row_a = next(line for line in lines if line.strip("│ ").startswith("a "))
    assert "cam0, ev0" in row_a
    assert " MB" in row_a
    assert any("junk" in line and "damaged" in line for line in lines)  # not a take: damaged


def test_empty_and_missing_directories(tmp_path: Path) -> None:
    r = runner.invoke(app, ["takes", str(tmp_path)])
    assert r.exit_code == 0
    assert "no takes in" in r.output
    r = runner.invoke(app, ["takes", str(tmp_path / "nope")])
    assert r.exit_code == 2
    assert "not a directory" in r.output
