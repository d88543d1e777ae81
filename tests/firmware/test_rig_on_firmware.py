"""The whole default rig on the firmware: `rigd capture --config deploy/configs/sim-rig-avr.toml`
runs the AVR image under simavr as the trigger box, on the virtual clock. Every sim camera and
event sensor sees the firmware's own edges; the take is complete, every frame and trigger-in
edge sits on its pulse (the sync residual is only the devices' own whole-microsecond stamps),
and two runs give the same take."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rigd.take import Take

REPO = Path(__file__).resolve().parents[2]
CONFIG = REPO / "deploy" / "configs" / "sim-rig-avr.toml"
DURATION_S = 1.0


def _capture(out: Path) -> Path:
    cmd = [sys.executable, "-m", "rigd.app.cli", "capture", "--config", str(CONFIG), "--duration"]
    cmd += [str(DURATION_S), "--out", str(out), "--json", "--local", "--strict"]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=900)
    assert done.returncode == 0, (
        f"rigd capture exited {done.returncode}:\n{done.stdout}\n{done.stderr[-4000:]}"
    )
    summary = json.loads(done.stdout)
    assert summary["verdict"] == "complete", summary
    return Path(summary["path"])


@pytest.mark.slow
def test_the_default_rig_on_the_firmware_is_complete_in_sync_and_the_same_twice(
    firmware_build: Path, harness_binary: Path, tmp_path: Path
) -> None:
    a, b = _capture(tmp_path / "a"), _capture(tmp_path / "b")
    with Take(a) as ta, Take(b) as tb:
        n = round(DURATION_S * 30)
        pa, pb = ta.pulses(), tb.pulses()
        assert pa.index.tolist() == list(range(n))
        assert np.array_equal(pa.t_us, pb.t_us)  # the firmware's clock: the same cycles twice
        assert np.array_equal(
            np.diff(pa.t_us), [round((k + 1) * 1e6 / 30) - round(k * 1e6 / 30) for k in range(n - 1)]
        )
        report = ta.sync_report
        assert report is not None
        assert not [loss for loss in report.losses if loss.count]
        assert report.pulses_seen_by_no_device == []
        for name, dev in report.devices.items():
            assert dev.n_matched == n, name
            # The firmware's edges carry no jitter: what is left is each device stamping whole
            # microseconds of its own drifting clock (the Python box with jitter_us=0 leaves the
            # same), under half a microsecond.
            assert dev.residual_max_us < 0.5, (name, dev.residual_max_us)
        for cam in ("cam0", "cam1", "cam2"):
            fa, fb = ta.camera(cam, demosaic=False), tb.camera(cam, demosaic=False)
            assert len(fa) == len(fb) == n
            assert np.array_equal(fa.timestamps_us, fb.timestamps_us)
            for i in (0, n // 2, n - 1):
                assert np.array_equal(fa[i].image, fb[i].image)
        for sensor in ("ev0", "ev1"):
            ea, eb = ta.sensor(sensor).events(), tb.sensor(sensor).events()
            assert len(ea) > 10_000
            for col in ("t", "x", "y", "p"):
                assert np.array_equal(getattr(ea, col), getattr(eb, col)), (sensor, col)
            assert np.array_equal(ta.sensor(sensor).triggers.t, tb.sensor(sensor).triggers.t)
