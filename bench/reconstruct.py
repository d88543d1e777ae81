"""`rigd reconstruct` end to end: Mev/s and peak memory per scheduler and worker count, and what
each knob keeps and costs, on a sim take and on the real recordings in ../shared/data/events/.

Each run is a fresh process (`rigd reconstruct ... --scheduler S --workers N`), so the numbers
include numba's compile time and the peak memory is that of the whole process tree (workers
included), sampled every 50 ms. The baseline is the previous main's workflow where `--baseline
REV` names a git revision (run from a worktree of it, with a time limit).

    python -m bench.reconstruct --take TAKE.h5 [--knobs-take SHORT.h5] [--real-data DIR] [--baseline REV]
    python -m bench.reconstruct --seconds 60     # captures the take first (virtual clock)
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import psutil

from rigd.take.reader import Take

REPO = Path(__file__).resolve().parent.parent


@dataclass
class Run:
    label: str
    wall_s: float
    peak_mb: float
    events: int
    kept: int
    segments: int
    ok: bool
    note: str = ""

    @property
    def mev_s(self) -> float:
        return self.events / self.wall_s / 1e6 if self.wall_s > 0 and self.ok else 0.0


def _peak_rss(proc: psutil.Process, stop: threading.Event, out: list[float]) -> None:
    peak = 0.0
    while not stop.is_set():
        try:
            procs = [proc, *proc.children(recursive=True)]
            rss = 0
            for p in procs:
                try:
                    rss += p.memory_info().rss
                except psutil.NoSuchProcess:
                    continue
            peak = max(peak, rss / 2**20)
        except psutil.NoSuchProcess:
            break
        stop.wait(0.05)
    out.append(peak)


def run_cli(label: str, take: Path, args: list[str], timeout_s: float, cwd: Path = REPO) -> Run:
    """One `rigd reconstruct` in a fresh process; events from the take, kept/segments from its output."""
    with tempfile.TemporaryDirectory() as out:
        cmd = [sys.executable, "-m", "rigd.app.cli", "reconstruct", str(take), "--out", out, *args]
        env = dict(os.environ, PYTHONPATH=str(cwd))
        t0 = time.perf_counter()
        popen = subprocess.Popen(
            cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        stop, peak = threading.Event(), []  # type: ignore[var-annotated]
        sampler = threading.Thread(target=_peak_rss, args=(psutil.Process(popen.pid), stop, peak))
        sampler.start()
        try:
            _, err = popen.communicate(timeout=timeout_s)
            ok, note = (
                popen.returncode == 0,
                "" if popen.returncode == 0 else err.strip().splitlines()[-1][:80],
            )
        except subprocess.TimeoutExpired:
            popen.kill()
            _, err = popen.communicate()
            ok, note = False, f"did not finish in {timeout_s:.0f} s"
        wall = time.perf_counter() - t0
        stop.set()
        sampler.join()
        kept = segments = 0
        for doc_path in Path(out).glob("*/segments.json"):  # this workflow: one document per take
            doc = json.loads(doc_path.read_text())
            kept = sum(s["events_kept"] for s in doc["sensors"].values())
            segments = len(doc["segments"])
        if not segments:  # the baseline: one document per sensor, kept counts in its output lines
            for doc_path in Path(out).glob("*/*/segments.json"):
                segments += len(json.loads(doc_path.read_text())["segments"])
            kept = sum(int(m.group(1)) for m in re.finditer(r"(\d+)/\d+ events kept", err if ok else ""))
    with Take(take) as t:
        events = sum(t.sensor(s).count for s in t.event_sensors)
    return Run(label, wall, peak[0] if peak else 0.0, events, kept, segments, ok, note)


def table(title: str, runs: list[Run]) -> None:
    print(f"\n{title}")
    cols = ("events", 11), ("wall s", 8), ("Mev/s", 7), ("peak MB", 8), ("kept %", 7), ("segments", 8)
    head = f"{'run':<44} " + " ".join(f"{c:>{w}}" for c, w in cols) + "  note"
    print(head)
    print("-" * len(head))
    for r in runs:
        kept = f"{100 * r.kept / r.events:.2f}" if r.ok and r.events else "-"
        segs = str(r.segments) if r.ok else "-"
        cells = f"{r.events:11,} {r.wall_s:8.1f} {r.mev_s:7.2f} {r.peak_mb:8.0f} {kept:>7} {segs:>8}"
        print(f"{r.label:<44} {cells}  {r.note}", flush=True)


def capture(seconds: float, out: Path) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    cmd = ["rigd", "capture", "--duration", str(seconds), "--out", str(out), "--sim-clock", "virtual"]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return max(out.glob("*.h5"), key=lambda p: p.stat().st_mtime)


def convert_real(data: Path, out: Path) -> list[Path]:
    """The real recordings as takes (`rigd convert`), skipping what is missing."""
    takes = []
    out.mkdir(parents=True, exist_ok=True)
    for src in sorted(data.glob("*.raw")) + sorted(data.glob("*.dat")):
        dest = out / f"{src.stem}.h5"
        if not dest.exists():
            subprocess.run(["rigd", "convert", str(src), str(dest)], check=True, stdout=subprocess.DEVNULL)
        takes.append(dest)
    return takes


KNOBS: list[tuple[str, list[str]]] = [
    ("paper: 30 us, r 3, support 2", []),
    ("--no-filter", ["--no-filter"]),
    ("--filter-window-us 100", ["--filter-window-us", "100"]),
    ("--filter-window-us 300", ["--filter-window-us", "300"]),
    ("--filter-window-us 1000", ["--filter-window-us", "1000"]),
    ("--filter-window-us 3000", ["--filter-window-us", "3000"]),
    ("--filter-radius 1", ["--filter-radius", "1"]),
    ("--filter-support 1", ["--filter-support", "1"]),
    ("--filter-support 4", ["--filter-support", "4"]),
    ("--threshold 0.5", ["--threshold", "0.5"]),
    ("--threshold 0.05 (1000 us filter)", ["--threshold", "0.05", "--filter-window-us", "1000"]),
    ("--e2i direct", ["--e2i", "direct"]),
    ("--map-scale 0.125", ["--map-scale", "0.125"]),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--take", type=Path, help="take for the scaling table (default: capture --seconds)")
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--knobs-take", type=Path, help="take for the knob table (default: --take)")
    ap.add_argument("--real-data", type=Path, default=REPO.parent / "shared" / "data" / "events")
    ap.add_argument("--baseline", help="git revision whose workflow is the baseline row")
    ap.add_argument("--timeout", type=float, default=900.0)
    ap.add_argument("--skip-scaling", action="store_true")
    ap.add_argument("--skip-knobs", action="store_true")
    a = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench-reconstruct-"))
    take = a.take or capture(a.seconds, work / "takes")
    with Take(take) as t:
        span = max((sp[1] - sp[0] if (sp := t.sensor(s).span) else 0) for s in t.event_sensors)
    print(
        f"take: {take} ({span / 1e6:.1f} s of events), {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}"
    )

    if not a.skip_scaling:
        runs = []
        for sched, workers in (("sync", 1), ("threads", 1), ("threads", 2), ("processes", 2)):
            args = ["--scheduler", sched] + ([] if sched == "sync" else ["--workers", str(workers)])
            runs.append(
                run_cli(f"{sched}, {workers} worker{'s' if workers > 1 else ''}", take, args, a.timeout)
            )
        if a.baseline:
            tree = work / "baseline"
            subprocess.run(["git", "worktree", "add", "-f", str(tree), a.baseline], cwd=REPO, check=True)
            try:
                runs.append(
                    run_cli(f"baseline {a.baseline[:10]} (per sensor, in memory)", take, [], a.timeout, tree)
                )
            finally:
                subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=REPO, check=True)
        table("Scaling: end to end per scheduler and worker count (fresh process, compile included)", runs)

    if not a.skip_knobs:
        knobs_take = a.knobs_take or take
        runs = [run_cli(label, knobs_take, ["--workers", "2", *args], a.timeout) for label, args in KNOBS]
        table(f"Knobs on the sim take {knobs_take.name} (threads, 2 workers)", runs)
        if a.real_data.is_dir():
            for real in convert_real(a.real_data, work / "real"):
                runs = [
                    run_cli(label, real, ["--workers", "2", *args], a.timeout) for label, args in KNOBS[:6]
                ]
                table(f"Knobs on the real recording {real.stem}", runs)


if __name__ == "__main__":
    main()
