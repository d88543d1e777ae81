"""`rigd status` / `rigd stop` run by a user who may not use the daemon's control socket (its
0700 runtime directory is another user's): one line that says so, never a traceback."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[4]
NOBODY = 65534


@pytest.mark.slow
@pytest.mark.parametrize("command", [["status"], ["stop"], ["capture", "--duration", "0.1"]])
def test_another_users_daemon_is_one_line(start_daemon: Any, tmp_path: Path, command: list[str]) -> None:
    setpriv = shutil.which("setpriv")
    if setpriv is None or os.geteuid() != 0:
        pytest.skip("needs root and setpriv (util-linux) to run the CLI as uid 65534")
    rd = start_daemon()
    endpoint = rd.config.service.control_endpoint
    cache = tmp_path / "numba"
    cache.mkdir()
    cache.chmod(0o1777)
    tmp_path.chmod(0o755)
    env = {
        **os.environ,
        "HOME": "/nonexistent",
        "NUMBA_CACHE_DIR": str(cache),
        "PYTHONDONTWRITEBYTECODE": "1",
    }
    r = subprocess.run(
        [
            setpriv,
            f"--reuid={NOBODY}",
            f"--regid={NOBODY}",
            "--clear-groups",
            sys.executable,
            "-m",
            "rigd.app.cli",
            *command,
            "--connect",
            endpoint,
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=REPO,
        env=env,
    )
    assert "Traceback" not in r.stderr, r.stderr
    assert r.returncode == 2, r.stdout + r.stderr
    assert "permission denied" in r.stderr
    assert "sudo -u" in r.stderr


_IMPORT_DECODERS = """
import sys
if sys.argv[1] == "ensure":
    from rigd.app.numba_cache import ensure_numba_cache
    print(ensure_numba_cache())
import rigd.evt.evt2  # compiles a cache=True kernel at import
print("decoders ready")
"""


@pytest.mark.slow
def test_a_user_without_a_writable_numba_cache_gets_a_private_one(tmp_path: Path) -> None:
    """No writable source tree, no home, no NUMBA_CACHE_DIR: numba raises at the first event
    decoder; the CLI's start points NUMBA_CACHE_DIR at a directory of the user's own."""
    setpriv = shutil.which("setpriv")
    if setpriv is None or os.geteuid() != 0:
        pytest.skip("needs root and setpriv (util-linux) to run as uid 65534")
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    tmp.chmod(0o1777)
    tmp_path.chmod(0o755)
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME")}
    env.update(HOME="/nonexistent", TMPDIR=str(tmp), PYTHONDONTWRITEBYTECODE="1")
    as_nobody = [setpriv, f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups", sys.executable, "-c"]
    runs = {
        how: subprocess.run(
            [*as_nobody, _IMPORT_DECODERS, how],
            capture_output=True,
            text=True,
            timeout=300,
            cwd=REPO,
            env=env,
        )
        for how in ("plain", "ensure")
    }
    assert "no locator available" in runs["plain"].stderr  # what `rigd capture` died of
    assert runs["ensure"].returncode == 0, runs["ensure"].stderr
    chosen, ready = runs["ensure"].stdout.splitlines()
    assert ready == "decoders ready"
    assert Path(chosen).name == f"rigd-numba-{NOBODY}"
    assert Path(chosen).stat().st_uid == NOBODY
    shutil.rmtree(chosen, ignore_errors=True)
