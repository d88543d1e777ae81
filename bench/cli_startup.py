"""How long `rigd` takes to start: `rigd --help`, `rigd status` (no daemon) and `rigd takes`.

    python -m bench.cli_startup [--repeat 5] [--baseline DIR]

Runs each command in a fresh process, round-robin so background load hits every command alike,
and reports wall and CPU (user + system) seconds: the median (the host is shared) and the best
run. CPU is the comparable figure on a loaded host. `--baseline DIR` times a second checkout of
rigd (e.g. `git archive main | tar -x -C DIR`) through the same interpreter, by PYTHONPATH, side by
side with this one. What each command imports on the way is checked by
tests/rigd/app/cli/test_lazy_imports.py, not here.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]
COMMANDS = (["--help"], ["status"], ["takes"])


def run_once(args: list[str], tree: Path, runtime: Path, takes: Path) -> tuple[float, float]:
    """(wall s, CPU s) of `rigd ARGS` in a fresh interpreter importing rigd from `tree`."""
    env = dict(os.environ, PYTHONPATH=str(tree), RIGD_RUNTIME_DIR=str(runtime))
    code = "import sys; from rigd.app.cli import main; sys.argv = ['rigd', *sys.argv[1:]]; main()"
    argv = [sys.executable, "-c", code, *args]
    if args == ["takes"]:
        argv.append(str(takes))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(
        argv, env=env, cwd=takes, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False
    )
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--baseline", type=Path, help="Another rigd source tree to time beside this one.")
    args = ap.parse_args()
    trees = {"this tree": HERE}
    if args.baseline is not None:
        trees = {"baseline": args.baseline.resolve(), **trees}
    runs: dict[tuple[str, str], list[tuple[float, float]]] = {}
    with tempfile.TemporaryDirectory(prefix="rigd-startup-") as tmp:
        runtime, takes = Path(tmp) / "run", Path(tmp)
        runtime.mkdir(mode=0o700)
        for _ in range(args.repeat):
            for label, tree in trees.items():
                for cmd in COMMANDS:
                    runs.setdefault((label, " ".join(cmd)), []).append(run_once(cmd, tree, runtime, takes))
    print(f"rigd start-up, {args.repeat} runs each, load average {os.getloadavg()[0]:.1f}")
    print("| tree | command | wall median s | wall best s | CPU median s | CPU best s |")
    print("|---|---|---|---|---|---|")
    for (label, name), got in runs.items():
        walls, cpus = [w for w, _ in got], [c for _, c in got]
        print(
            f"| {label} | rigd {name} | {statistics.median(walls):.2f} | {min(walls):.2f} | "
            f"{statistics.median(cpus):.2f} | {min(cpus):.2f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
