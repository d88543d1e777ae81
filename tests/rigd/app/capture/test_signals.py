"""An in-process `rigd capture` ends its take cleanly on SIGINT, SIGTERM and SIGHUP, says where
the take is, and leaves no disk ballast behind; ballast of killed captures is cleaned."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import h5py
import pytest

from rigd.app.capture.ballast import Ballast, remove_stale_ballast
from rigd.app.config import RigConfig, default_sim_rig


def _small_rig(path: Path) -> Path:
    cfg = default_sim_rig(world=f"sig-{uuid.uuid4().hex[:8]}", resolution=(160, 120))
    data = cfg.model_dump(mode="json")
    data["writer"].update({"disk_reserve_mb": 0, "disk_ballast_mb": 24})
    out = path / "rig.json"
    out.write_text(RigConfig.from_data(data).model_dump_json())
    return out


def _wait_for_data(out_dir: Path, proc: subprocess.Popen[str], deadline_s: float = 60.0) -> Path:
    """The take file, once it holds a few MB (frames are flowing); fails if the capture ends.

    A state to wait for, polled, with a deadline generous for a loaded machine. The capture
    runs on the real clock on purpose: an end-to-end run of the CLI that a signal interrupts
    (on virtual time its 120 s could run out before the signal)."""
    deadline = time.monotonic() + deadline_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        takes = list(out_dir.glob("*.h5"))
        if takes and takes[0].stat().st_size > 2_000_000:
            return takes[0]
        time.sleep(0.05)
    pytest.fail("no take data within the deadline")


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT])
def test_signal_stops_the_take_cleanly_and_names_it(tmp_path: Path, sig: signal.Signals) -> None:
    out_dir = tmp_path / "takes"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "rigd.app.cli",
            "capture",
            "--local",
            "--config",
            str(_small_rig(tmp_path)),
            "--duration",
            "120",
            "--out",
            str(out_dir),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    try:
        take = _wait_for_data(out_dir, proc)
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + sig, stderr
    assert f"take: {take}" in stdout
    assert f"stopped by {sig.name}: take {take} was finalized" in " ".join(stderr.split())
    with h5py.File(take) as f:
        assert f.attrs["status"] == "complete"
        assert sig.name in str(f.attrs["end_reason"])
    assert not list(out_dir.glob(f"{Ballast.PREFIX}*"))


def test_stale_ballast_of_killed_processes_is_removed(tmp_path: Path) -> None:
    gone = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    )
    dead_pid = int(gone.stdout)
    stale = tmp_path / f"{Ballast.PREFIX}{dead_pid}-0123abcd"
    legacy = tmp_path / f"{Ballast.PREFIX}89abcdef"  # written before names carried a PID
    live = tmp_path / f"{Ballast.PREFIX}{os.getpid()}-fedcba98"
    for p in (stale, legacy, live):
        p.write_bytes(b"\0" * 16)
    assert remove_stale_ballast(tmp_path) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == [live.name]
