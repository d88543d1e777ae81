"""Root conftest: its presence (with tests/__init__.py) puts the repo root on sys.path under
pytest's default import mode, so tests import the checkout's packages and a few helper modules
of their own (`from tests.drivers.fake_aravis import ...`) with plain `pytest`. Scenario
builders shared with the benches live in the testing packages: `drivers.testing` (device
contract suites, EVT streams), `firmware_sim.testing` (synthetic takes and scenes) and
`rigd.app.testing` (board captures, daemons, the console, crashed writers). A conftest is
never imported as a module, nor a test module by another."""

from __future__ import annotations

import logging
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest


@pytest.fixture(autouse=True)
def _restore_root_logging() -> Iterator[None]:
    """Commands under test call `setup_logging`, which puts a stderr handler on the root logger;
    left there, it writes into a stream pytest has since closed, and every later test that
    logs gets a "Logging error" traceback on its stderr. Each test starts and ends with the
    root logger as it found it."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    for handler in [h for h in root.handlers if h not in handlers]:
        root.removeHandler(handler)
        handler.close()
    root.setLevel(level)


@pytest.fixture
def mount_tmpfs(tmp_path: Path) -> Iterator[Callable[[str], Path]]:
    """Mount a tmpfs of the given size (`"30m"`) under tmp_path: a disk that fills. Skips where
    mounting is not allowed; unmounted after the test."""
    mounted: list[Path] = []

    def mount(size: str) -> Path:
        where = tmp_path / f"disk{len(mounted)}"
        where.mkdir()
        run = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
            capture_output=True,
            text=True,
        )
        if run.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here ({run.stderr.strip() or 'mount failed'})")
        mounted.append(where)
        return where

    try:
        yield mount
    finally:
        for where in mounted:
            subprocess.run(["umount", "-l", str(where)], check=False)
