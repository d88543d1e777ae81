"""`pip install rigd` without extras reads a whole take: events (EVT words decoded by numba),
triggers, Bayer mosaics as stored, calibration and the summary, with none of the rig's
libraries importable; demosaicing asks for the `frames` extra by name."""

from __future__ import annotations

import json
import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from firmware_sim.world import reset_world
from rigd.app.capture import run_capture
from rigd.app.config import default_sim_rig
from rigd.core.extras import OPTIONAL
from rigd.take import open_take

# Every optional library made unimportable, as in a fresh `pip install rigd`: the scripts below
# run with the comma-separated names in their last argument blocked.
LEAN = """
import sys
BLOCKED = set(sys.argv[-1].split(","))
class Lean:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
sys.meta_path.insert(0, Lean())
"""
LEAN_READ = (
    LEAN
    + """
import json
from rigd.core.errors import MissingExtraError
from rigd.take import open_take
out = {}
with open_take(sys.argv[1]) as take:
    out["status"] = take.status
    out["events"] = {s: int(len(take.sensor(s).events())) for s in take.event_sensors}
    out["triggers"] = {s: int(len(take.sensor(s).triggers.t)) for s in take.event_sensors}
    out["mosaics"] = {c: list(take.camera(c, demosaic=False).raw(0).shape) for c in take.cameras}
    out["calibrated"] = sorted(take.calibration or {})
    out["verdict"] = take.summary().verdict
    try:
        take.camera(take.cameras[0]).rgb(0)
    except MissingExtraError as exc:
        out["demosaic"] = str(exc)
out["loaded"] = sorted(m for m in BLOCKED if m in sys.modules)
print(json.dumps(out))
"""
)


LEAN_CLI = (
    LEAN
    + """
from rigd.app.cli import main
sys.argv = ["rigd", "-v", "capture", "--duration", "1"]
main()
"""
)


def test_the_rig_on_a_lean_install_names_the_extra_to_install(tmp_path: Path) -> None:
    run = subprocess.run(
        [sys.executable, "-c", LEAN_CLI, ",".join(sorted(OPTIONAL))],
        capture_output=True,
        text=True,
        check=False,
        cwd=tmp_path,
    )
    assert run.returncode == 2, run.stderr
    assert "error: `rigd capture` needs" in run.stderr
    assert "pip install 'rigd[" in run.stderr
    assert "Traceback" not in run.stderr
    assert not (tmp_path / "takes").exists()  # refused before anything was made


@pytest.fixture(scope="module")
def take_path(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    world = f"t-lean-{uuid.uuid4().hex[:8]}"
    cfg = default_sim_rig(world=world, resolution=(160, 90), pixel_format="bayer_rg8", clock="virtual")
    yield run_capture(cfg, tmp_path_factory.mktemp("lean"), 0.3).path
    reset_world(world)


@pytest.mark.slow
def test_a_take_reads_without_any_extra(take_path: Path) -> None:
    blocked = ",".join(sorted(OPTIONAL))
    run = subprocess.run(
        [sys.executable, "-c", LEAN_READ, str(take_path), blocked],
        capture_output=True,
        text=True,
        check=False,
    )
    assert run.returncode == 0, run.stderr
    lean = json.loads(run.stdout)
    with open_take(take_path) as take:  # the same take, read with everything installed
        assert lean["status"] == take.status == "complete"
        assert lean["events"] == {s: len(take.sensor(s).events()) for s in take.event_sensors}
        assert all(n > 0 for n in lean["events"].values())
        assert lean["triggers"] == {s: len(take.sensor(s).triggers.t) for s in take.event_sensors}
        assert lean["mosaics"] == {c: [90, 160] for c in take.cameras}
        assert lean["calibrated"] == sorted(take.calibration or {})
        assert lean["verdict"] == take.summary().verdict
    assert lean["loaded"] == []
    assert "pip install 'rigd[frames]'" in lean["demosaic"]
