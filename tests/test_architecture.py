"""The layering drawn in docs/architecture.md is the code's, and no import runs up a layer."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_the_import_graph_runs_only_down_and_the_doc_draws_it() -> None:
    run = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "import_graph.py"), "--check"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert run.returncode == 0, run.stderr


def test_an_upward_import_is_caught() -> None:
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        import import_graph
    finally:
        sys.path.remove(str(ROOT / "tools"))
    stack = [["rigd.app"], ["rigd.products", "firmware_sim"], ["rigd.core"]]
    counts = import_graph.collections.Counter(
        {("rigd.core", "rigd.app"): 1, ("rigd.products", "firmware_sim"): 2, ("rigd.app", "rigd.core"): 5}
    )
    bad = import_graph.wrong_way(stack, counts)
    assert bad == [
        "rigd.core -> rigd.app: 1 import(s) run up a layer",
        "rigd.products -> firmware_sim: 2 import(s) between siblings that must be independent",
    ]
