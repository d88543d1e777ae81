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
    """A take whose writer filled the disk before its first flush with no ballast to close in:
    its header records an end before the data its datasets point to."""
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
    # Frames go to the file as their own chunks (no chunk cache): what fails afterwards is
    # HDF5 flushing its metadata onto the full disk, reported as ENOSPC or as EIO.
    with pytest.raises(OSError, match=r"No space left|Unable to flush"):
        w.fail("disk full")
    with pytest.raises(OSError, match=r"No space left|Unable to flush"):
        w.close()
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
        assert f"rigd recover {copy}" in lines[0]
    before = copy.read_bytes()
    rec = runner.invoke(app, ["recover", str(copy)])
    assert rec.exit_code != 0, rec.output
    assert "Traceback" not in rec.output
    assert "recovery saved nothing of this take and left the file as it was" in rec.output, rec.output
    assert copy.read_bytes() == before
    assert os.path.getsize(copy) > 0
