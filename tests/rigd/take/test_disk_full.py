"""A full disk never leaves an unreadable take.

A take on a full disk is closed in the room its released ballast makes, so the ballast must
hold what closing writes (`rigd.app.capture.ballast.minimum_ballast_bytes`): less is refused
up front, in one line naming `writer.disk_ballast_mb` and the minimum. At the minimum, the
default sim rig filling a small tmpfs (before its first flush, the hardest case) leaves a take
`rigd inspect` reads and `rigd recover` seals. A file damaged anyway (another writer, an
older rigd) makes `rigd inspect` say so in one line, never crash, and `rigd recover` say that
it saved nothing.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from rigd.app.capture.ballast import minimum_ballast_bytes
from rigd.app.cli import app
from rigd.app.config import RigConfig, default_sim_rig
from rigd.core.devices import DeviceInfo
from rigd.core.frames import Frame
from rigd.core.settings import WriterConfig
from rigd.take.seal import fail_take
from rigd.take.writer import TakeWriter

pytestmark = pytest.mark.slow


@pytest.fixture
def small_disk(mount_tmpfs: Callable[[str], Path]) -> Path:
    return mount_tmpfs("30m")


def _default_rig_minimum_mb() -> int:
    """The default sim rig: three 1280x720 RGB cameras and two event sensors."""
    return math.ceil(minimum_ballast_bytes(WriterConfig(), [1280 * 720 * 3] * 3, 2) / 1e6)


def _rig_file(where: Path, ballast_mb: int) -> Path:
    cfg = default_sim_rig(world=f"df-{uuid.uuid4().hex[:8]}")
    data = cfg.model_dump(mode="json")
    data["writer"].update({"disk_reserve_mb": 0, "disk_ballast_mb": ballast_mb})
    path = where / "rig.json"
    path.write_text(RigConfig.from_data(data).model_dump_json())
    return path


def test_a_ballast_below_what_closing_needs_is_refused_in_one_line(tmp_path: Path) -> None:
    need = _default_rig_minimum_mb()
    res = CliRunner().invoke(
        app, ["capture", "--local", "-c", str(_rig_file(tmp_path, need - 1)), "-o", str(tmp_path / "t")]
    )
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert lines[-1].startswith("error: not starting a take: writer.disk_ballast_mb = "), res.stderr
    assert f"below the {need} MB this rig needs" in lines[-1]
    assert f"set it to at least {need}" in lines[-1]
    assert "Traceback" not in res.output
    assert not list((tmp_path / "t").glob("*.h5")), "a refused take must not leave a file"
    assert not list((tmp_path / "t").glob(".rigd-ballast-*")), "nor its ballast"


def test_the_default_rig_filling_a_small_disk_leaves_a_take_that_reads_and_recovers(small_disk: Path) -> None:
    need = _default_rig_minimum_mb()
    runner = CliRunner()
    rig = _rig_file(small_disk.parent, need)
    res = runner.invoke(app, ["capture", "--local", "-c", str(rig), "-o", str(small_disk), "-d", "20"])
    assert res.exit_code == 2, res.output
    assert "disk full" in res.stderr, res.stderr
    assert "rigd recover" in res.stderr, res.stderr
    assert "Traceback" not in res.output
    [take] = list(small_disk.glob("*.h5"))
    assert not list(small_disk.glob(".rigd-ballast-*"))

    # Before recovery: readable, says it failed and that `rigd recover` seals it (exit 1).
    seen = runner.invoke(app, ["inspect", str(take)])
    assert seen.exit_code == 1, seen.output
    assert "Traceback" not in seen.output
    assert seen.stdout.splitlines()[0].startswith("verdict: failed — "), seen.stdout
    assert f"rigd recover {take}" in seen.stderr
    as_json = runner.invoke(app, ["inspect", "--json", str(take)])
    assert as_json.exit_code == 1, as_json.output
    assert json.loads(as_json.stdout)["status"] == "failed"

    # Recovery on the same disk, as it is (only what closing did not use of the ballast is free).
    rec = runner.invoke(app, ["recover", str(take)])
    assert "Traceback" not in rec.output
    assert rec.exit_code == 0, rec.output
    assert "SEALED" in rec.stdout, rec.stdout
    assert "recorded as lost" in rec.stdout or "holds no recorded data" in rec.stdout, rec.stdout
    after = runner.invoke(app, ["inspect", "--json", str(take)])
    assert "Traceback" not in after.output
    summary = json.loads(after.stdout)
    # Sealed complete (what was flushed, with what came after it recorded as lost) or, when
    # no flush ever reached the disk, sealed failed with the reason: never complete and whole.
    assert summary["verdict"] in ("degraded", "failed"), summary
    assert summary["verdict_reasons"], summary


def _damaged_take(disk: Path) -> Path:
    """A take an older rigd left on a full disk with no ballast to close in: it flushed the
    take's metadata onto the full disk when marking it failed, and HDF5 wrote part of it, so the
    header records an end before the data its datasets point to. (This writer tries no flush
    once the file refuses writes: the take stays as last flushed, whole.)"""
    path = disk / "damaged.h5"
    w = TakeWriter(path, rig_config_json="{}", take_id="damaged", config=WriterConfig(), rigd_version="t")
    shape = (720, 1280, 3)
    for c in range(3):
        w.add_camera(f"cam{c}", DeviceInfo(kind="rgb_camera", spec=f"test://cam{c}"), shape, np.uint8, "{}")
    img = np.random.default_rng(0).integers(0, 255, shape, dtype=np.uint8)
    with pytest.raises(OSError, match="No space left"):  # noqa: PT012 - the disk fills in the loop
        for i in range(1000):
            for c in range(3):
                w.append_frame(f"cam{c}", Frame(img, 1000 * i, 100, i, i))
    # What an older writer's `fail` did: write its buffers, then flush, onto the full disk.
    with pytest.raises(OSError, match="No space left"):
        w.state.write_all()
    w.state.f.attrs["status"] = "failed"
    with pytest.raises(RuntimeError, match="Unable to flush"):
        w.state.f.flush()
    with pytest.raises(OSError, match="No space left"):
        w.close()  # HDF5 cannot close it any more ("slist already enabled"): kept until exit
    return path


def test_inspect_never_crashes_on_a_take_a_full_disk_damaged(small_disk: Path) -> None:
    path = _damaged_take(small_disk)
    copy = small_disk.parent / "damaged.h5"
    shutil.copy(path, copy)
    runner = CliRunner()
    for args in ([], ["--json"]):
        res = runner.invoke(app, ["inspect", *args, str(copy)])
        assert res.exit_code == 2, res.output
        assert "Traceback" not in res.output
        lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1, res.stderr
        assert lines[0].startswith(f"error: {copy}: damaged"), lines[0]
        # What recovery can do: the data HDF5 cannot read ("`rigd recover PATH` seals what is
        # left"), or a header HDF5 refuses to open ("`rigd recover` cannot repair it").
        assert "`rigd recover" in lines[0], lines[0]
    before = copy.read_bytes()
    rec = runner.invoke(app, ["recover", str(copy)])
    assert rec.exit_code != 0, rec.output
    assert "Traceback" not in rec.output
    saved_nothing = ("recovery saved nothing of this take and left the file as it was", "cannot repair it")
    assert any(said in rec.output for said in saved_nothing), rec.output
    assert copy.read_bytes() == before
    assert os.path.getsize(copy) > 0


def test_a_writer_the_full_disk_refuses_leaves_the_take_as_last_flushed_and_closes(
    small_disk: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """No ballast to close in: `fail` finds its writes refused and tries no flush (one that
    fails half way leaves HDF5 unable to close the file), so the take stays whole as last
    flushed, `close` closes it, and recovery seals it."""
    path = small_disk / "refused.h5"
    w = TakeWriter(path, rig_config_json="{}", take_id="refused", config=WriterConfig(), rigd_version="t")
    shape = (720, 1280, 3)
    w.add_camera("cam0", DeviceInfo(kind="rgb_camera", spec="test://cam0"), shape, np.uint8, "{}")
    img = np.random.default_rng(0).integers(0, 255, shape, dtype=np.uint8)
    w.append_frame("cam0", Frame(img, 0, 100, 0, 0))
    w.flush()
    with pytest.raises(OSError, match="No space left"):  # noqa: PT012 - the disk fills in the loop
        for i in range(1, 1000):
            w.append_frame("cam0", Frame(img, 1000 * i, 100, i, i))
    with pytest.raises(OSError, match="No space left"):
        fail_take(w, "disk full")
    with pytest.raises(OSError, match="No space left"):
        w.close()
    assert "could not be closed" not in caplog.text  # closed, its lock released
    seen = CliRunner().invoke(app, ["inspect", "--json", str(path)])
    assert seen.exit_code == 1, seen.output
    assert json.loads(seen.stdout)["status"] == "recording"  # as last flushed
    rec = CliRunner().invoke(app, ["recover", str(path)])
    assert rec.exit_code == 0, rec.output
    assert "SEALED" in rec.stdout, rec.stdout


def test_a_disk_full_before_the_first_flush_says_so_in_one_line(
    mount_tmpfs: Callable[[str], Path], tmp_path: Path
) -> None:
    """No disk reserve, a disk that fills before the first flush: the error is one line (HDF5's
    message spans several), and it says the take holds no recorded data rather than sending the
    operator to `rigd recover`, which would find nothing to seal."""
    disk = mount_tmpfs("48m")
    rig = _rig_file(tmp_path, _default_rig_minimum_mb())
    res = CliRunner().invoke(app, ["capture", "--local", "-c", str(rig), "-o", str(disk), "-d", "20"])
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    # Each log record and the error are one line each: no continuation of a multi-line message.
    assert all(re.match(r"\d{4}-\d\d-\d\dT|error: ", ln) for ln in lines), res.stderr
    [line] = [ln for ln in lines if ln.startswith("error: ")]
    assert "disk full" in line
    if "before its first flush" in line:  # the case of the issue: nothing reached the disk whole
        assert "holds no recorded data" in line
        assert "MB were written" in line
        assert "cannot bring any back" in line
        assert "run `rigd recover` to seal it" not in line
    else:  # a flush made it first: what it wrote is there, and recovery seals it
        assert "run `rigd recover` to seal it" in line
