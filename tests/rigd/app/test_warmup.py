"""The warm-up: `is_warm` reads its stamp as numba reads its cache, and the README's first
capture on a cold numba cache warms up first and keeps everything."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from rigd.app import warmup as warmup_mod
from rigd.app.cli import app
from rigd.app.commands.warmup import run_warmup
from rigd.app.warmup import STAMP_VERSION, is_warm, stamp_path
from rigd.core.errors import DeviceError


def _stamp(tmp_path: Path, **change: object) -> Path:
    source = tmp_path / "kernels.py"
    source.write_text("x = 1\n")
    index = tmp_path / "kernels.kernel-1.py311.nbi"
    index.write_bytes(b"index")
    st = source.stat()
    entry = {"kernel": "kernels.kernel", "index": str(index), "source": str(source)}
    entry.update({"mtime": st.st_mtime, "size": st.st_size})
    entry.update(change)
    path = tmp_path / "stamp.json"
    path.write_text(json.dumps({"version": STAMP_VERSION, "kernels": [entry]}))
    return path


def test_a_stamp_whose_kernels_are_cached_is_warm(tmp_path: Path) -> None:
    assert is_warm(_stamp(tmp_path))


def test_no_stamp_is_cold(tmp_path: Path) -> None:
    assert not is_warm(tmp_path / "absent.json")


def test_an_empty_or_old_stamp_is_cold(tmp_path: Path) -> None:
    path = tmp_path / "stamp.json"
    path.write_text(json.dumps({"version": STAMP_VERSION, "kernels": []}))
    assert not is_warm(path)
    path.write_text(json.dumps({"version": STAMP_VERSION - 1, "kernels": [{"kernel": "k"}]}))
    assert not is_warm(path)


def test_a_corrupt_stamp_is_cold_and_said(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "stamp.json"
    path.write_text("{not json")
    assert not is_warm(path)
    assert "unreadable warm-up stamp" in caplog.text


def test_a_deleted_cache_index_is_cold(tmp_path: Path) -> None:
    path = _stamp(tmp_path)
    (tmp_path / "kernels.kernel-1.py311.nbi").unlink()
    assert not is_warm(path)


def test_a_changed_source_is_cold(tmp_path: Path) -> None:
    """numba recompiles a kernel whose source's size or mtime changed: so must the warm-up."""
    path = _stamp(tmp_path)
    (tmp_path / "kernels.py").write_text("x = 12\n")
    assert not is_warm(path)


def test_the_stamp_lives_in_the_numba_cache_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert stamp_path().parent == tmp_path
    assert not is_warm()  # a new, empty cache directory is cold


def _failing_warm_up(*_a: object) -> None:
    raise DeviceError("sim trigger box: no pty here")


def test_rigd_warmup_fails_with_the_reason(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(warmup_mod, "is_warm", lambda: False)
    monkeypatch.setattr(warmup_mod, "warm_up", _failing_warm_up)
    res = CliRunner().invoke(app, ["warmup"])
    assert res.exit_code == 2
    assert "error: sim trigger box: no pty here" in res.output


def test_a_capture_goes_on_when_its_warm_up_fails_and_says_so(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Before a capture the warm-up is a help, not a condition: the devices' preflight still
    compiles what each runs (a real rig on a host where the sim rig cannot run)."""
    monkeypatch.setattr(warmup_mod, "warm_up", _failing_warm_up)
    run_warmup("cold cache", required=False)
    err = capsys.readouterr().err
    assert "warm-up failed, capturing without it: sim trigger box: no pty here" in err


#: Compiling every kernel from nothing takes tens of seconds on an idle machine, minutes on a
#: loaded one; the bound only turns a hang into a failure.
_TIMEOUT_S = 900


@pytest.mark.slow
@pytest.mark.timeout(2 * _TIMEOUT_S + 60)
def test_readme_first_capture_on_a_cold_cache_warms_up_and_is_complete(tmp_path: Path) -> None:
    """The README's `rigd capture --duration 5 --out takes`, in-process, from an empty
    NUMBA_CACHE_DIR: it warms up first (progress lines), then the take keeps everything; the
    next capture finds the cache warm and does not warm up again."""
    cache = tmp_path / "numba-cache"
    cache.mkdir()
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    cmd = [sys.executable, "-m", "rigd.app.cli", "capture", "--local", "--duration", "5", "--out", "takes"]
    run = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=_TIMEOUT_S)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "warm-up: numba's cache lacks the capture path's kernels" in run.stderr, run.stderr[-3000:]
    assert "warm-up: done in" in run.stderr, run.stderr[-3000:]
    assert "rigd.evt.evt3_scan.scan_kernel compiled" in run.stderr, run.stderr[-3000:]
    assert run.stdout.splitlines()[0].startswith("verdict: complete"), run.stdout[-3000:]
    assert is_warm(stamp_path_in(cache))

    warm = subprocess.run(
        [sys.executable, "-m", "rigd.app.cli", "warmup"],
        env=env,
        capture_output=True,
        text=True,
        timeout=_TIMEOUT_S,
    )
    assert warm.returncode == 0, warm.stderr[-3000:]
    assert "holds every kernel" in warm.stderr, warm.stderr


def stamp_path_in(cache: Path) -> Path:
    (found,) = cache.glob("rigd-warmup-*.json")
    return found
