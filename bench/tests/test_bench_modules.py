"""Every bench module imports (mypy does not check bench/, so a renamed function would otherwise
only show when somebody runs the bench), and the gather bench runs end to end on a small part."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1]
MODULES = sorted(p.stem for p in BENCH.glob("*.py") if p.stem != "__init__")
#: Optional extras a bench may need (pyproject's `torch` extra): missing, the module is skipped.
OPTIONAL = {"torch"}


@pytest.mark.parametrize("name", MODULES)
def test_bench_module_imports(name: str) -> None:
    try:
        importlib.import_module(f"bench.{name}")
    except ModuleNotFoundError as exc:
        if exc.name not in OPTIONAL:
            raise
        pytest.skip(f"bench.{name} needs {exc.name}, not installed")


def test_gather_bench_copies_a_small_part() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "bench.gather", "--mb", "2", "--repeat", "1"],
        cwd=BENCH.parent,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert out.returncode == 0, out.stderr
    assert "| rigd takes gather copy (stat + reads + sha256 + rename) |" in out.stdout
