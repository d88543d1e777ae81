"""Soak: `rigd serve` capturing the sim rig for many minutes, memory and drops watched.

    python -m bench.soak [--minutes 10] [--take-s 60] [--resolution 640x360] [--keep] [--out DIR]

The daemon runs in its own process (as under systemd) and is driven over its control
socket: back-to-back takes of `--take-s` seconds until `--minutes` are up. For every take
the table shows frames per camera, events, pulses, the losses the take reports, and the
*unreported* drops (pulses a camera has no frame for that neither the sync report nor a
loss record accounts for: must be 0), with the daemon's resident memory back at idle after
the take and its peak during it. Each take is
deleted after it is checked unless `--keep` (10 min at 1280x720 would be ~140 GB).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from math import nan
from pathlib import Path
from typing import Any

import h5py
import psutil

from rigd.app.config import default_sim_rig
from rigd.app.service.client import DaemonClient, find_daemon
from rigd.take import open_take


def _check_take(path: Path) -> dict[str, Any]:
    with h5py.File(path, "r") as f:
        report = json.loads(f["sync/report_json"][()])
        pulses = int(f["trigger/pulses/index"].shape[0])
        frames = {c: int(f[f"frames/{c}/images"].shape[0]) for c in f["frames"]}
        status = str(f.attrs["status"])
    with open_take(path) as take:  # either event layout (columns, EVT words)
        events = sum(take.sensor(s).count for s in take.event_sensors)
    emitted = int(report.get("pulses_emitted") or pulses)
    unreported = 0
    for cam, n in frames.items():
        missing = len(report["devices"].get(cam, {}).get("missing_pulses", []))
        unreported += max(0, emitted - n - missing)
    losses = sum(int(r["count"]) for r in report["losses"])
    return {
        "status": status,
        "pulses": pulses,
        "frames_min": min(frames.values()),
        "events": events,
        "losses": losses,
        "loss_records": len(report["losses"]),
        "unreported": unreported,
        "reasons": sorted(
            {f"{r['device']}: {r['count']} {r['what']}, {r['reason']}" for r in report["losses"]}
        ),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--take-s", type=float, default=60.0)
    ap.add_argument("--resolution", default="640x360")
    ap.add_argument("--keep", action="store_true")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    w, h = (int(v) for v in args.resolution.split("x"))
    out = args.out or Path(tempfile.mkdtemp(prefix="rigd-soak-"))
    out.mkdir(parents=True, exist_ok=True)
    runtime = Path(tempfile.mkdtemp(prefix="rigd-soak-rt-"))
    os.chmod(runtime, 0o700)
    cfg = default_sim_rig(world="soak", resolution=(w, h))
    data = cfg.model_dump(mode="json")
    data["service"].update(
        {
            "take_dir": str(out),
            "control": f"ipc://{runtime}/control.sock",
            "telemetry": f"ipc://{runtime}/telemetry.sock",
            "metrics_port": None,
        }
    )
    cfg_path = runtime / "rig.json"
    cfg_path.write_text(json.dumps(data))
    log_path = out / "daemon.log"
    with log_path.open("ab") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "rigd.app.cli", "serve", "--config", str(cfg_path)], stdout=log, stderr=log
        )
    endpoint = f"ipc://{runtime}/control.sock"
    deadline = time.monotonic() + 60
    while (found := find_daemon(endpoint, timeout_s=0.5)) is None:
        if proc.poll() is not None or time.monotonic() > deadline:
            sys.exit(f"daemon did not start; see {log_path}")
        time.sleep(0.2)
    found.close()
    ps = psutil.Process(proc.pid)
    rss: list[float] = []
    stop = threading.Event()

    def sample() -> None:
        while not stop.wait(1.0):
            rss.append(ps.memory_info().rss / 1e6)

    threading.Thread(target=sample, daemon=True).start()
    rig = f"3 cams + 2 event sensors at {w}x{h}, 30 Hz"
    print(f"soak: {args.minutes:g} min of {args.take_s:g} s takes, rig {rig}")
    head = (
        f"{'take':>4} {'s':>5} {'status':>8} {'pulses':>6} {'frames':>6} {'Mev':>7} {'lost':>5} {'unrep':>5} "
    )
    print(head + f"{'RSS MB':>7} {'peak':>7} {'MB/s':>6}")
    client = DaemonClient(endpoint, timeout_s=30)
    t_end = time.monotonic() + args.minutes * 60
    totals = {"unreported": 0, "losses": 0, "takes": 0}
    rss_per_take: list[float] = []
    try:
        i = 0
        while time.monotonic() < t_end:
            t0 = time.monotonic()
            take = Path(
                client.call("capture", timeout_s=120.0, duration_s=args.take_s, label=f"soak{i}")["take"]
            )
            while True:
                st = client.call("status")
                if st["state"] == "idle" and st.get("last_take", {}).get("path") == str(take):
                    break
                time.sleep(0.5)
            wall = time.monotonic() - t0
            size = take.stat().st_size
            row = _check_take(take)
            # Resident size back at idle (the daemon has reaped the take), and the peak during it.
            time.sleep(0.5)
            rss_now = ps.memory_info().rss / 1e6
            rss_peak = max(rss[-int(wall) :] or [rss_now])
            rss_per_take.append(rss_now)
            print(
                f"{i:>4} {wall:>5.1f} {row['status']:>8} {row['pulses']:>6} {row['frames_min']:>6} "
                f"{row['events'] / 1e6:>7.2f} {row['losses']:>5} {row['unreported']:>5} "
                f"{rss_now:>7.1f} {rss_peak:>7.1f} "
                f"{size / 1e6 / wall:>6.1f}",
                flush=True,
            )
            for reason in row["reasons"]:
                print(f"       loss: {reason}")
            totals["unreported"] += row["unreported"]
            totals["losses"] += row["losses"]
            totals["takes"] += 1
            if not args.keep:
                take.unlink()
            i += 1
    finally:
        client.close()
        stop.set()
        proc.terminate()
        proc.wait(timeout=120)
        shutil.rmtree(runtime, ignore_errors=True)
    half = max(1, len(rss_per_take) // 2)
    first = statistics.median(rss_per_take[:half])
    second = statistics.median(rss_per_take[half:] or [nan])
    print(f"takes {totals['takes']}, losses {totals['losses']}, unreported drops {totals['unreported']}")
    print(
        f"daemon RSS min {min(rss):.1f} / max {max(rss):.1f} MB; idle after a take: median over the first "
        f"half {first:.1f} MB, the second half {second:.1f} MB; daemon exit code {proc.returncode}"
    )


if __name__ == "__main__":
    main()
