"""The layering drawn in docs/architecture.md is the code's, no import runs up a layer, and no module
or class outgrows the size the architecture steps set."""

from __future__ import annotations

import ast
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


#: Where the project's own code lives (tests and the generated build trees are not counted).
PACKAGES = ("rigd", "drivers", "calibration", "reconstruction", "firmware_sim", "bench", "tools")
#: The size bounds of the architecture steps: a module a reader can hold, a class with one job.
MAX_MODULE_LINES = 600
MAX_PUBLIC_METHODS = 25


def _sources() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))


def test_no_module_is_over_its_size() -> None:
    big = {
        str(p.relative_to(ROOT)): n
        for p in _sources()
        if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES
    }
    assert big == {}, f"modules over {MAX_MODULE_LINES} lines: split them along what they hold"


def test_no_class_has_more_public_methods_than_one_job_needs() -> None:
    wide = {}
    for path in _sources():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ClassDef):
                public = [
                    b.name
                    for b in node.body
                    if isinstance(b, ast.FunctionDef | ast.AsyncFunctionDef) and not b.name.startswith("_")
                ]
                if len(public) > MAX_PUBLIC_METHODS:
                    wide[f"{path.relative_to(ROOT)}:{node.name}"] = len(public)
    assert wide == {}, f"classes with over {MAX_PUBLIC_METHODS} public methods"
