"""What open web consoles and a busy host cost the capture: the default rig through the daemon.

    python -m bench.console_clients [--duration 8] [--resolution 1280x720] [--clients 0,1,10]
        [--load 0,1,2] [--stop-after S]

Runs the daemon with its web console in this process on the sim rig (real time, the default
rig's bayer_rg8 cameras unless `--pixel-format`) and, for each background load and client count,
one take of `--duration` seconds while that many clients behave like a dashboard tab (sending the
console's secret, as a logged-in browser does): each follows the live stream (server-sent events,
/api/live) and fetches the preview JPEG of every device whose version changed, one fetch at a
time, as the page does. `--load N` runs N busy processes at normal priority beside the daemon
(other work on the host), so the table shows where this machine stops holding the rig.
`--stop-after S` stops each take with the daemon's `stop` command after S seconds (what `rigd stop`
sends) and reports how long the stop took until the take was finalized.

Prints per level: the host's load average, frames/s and events/s written, frames and events lost
(loss records' counts), the take's verdict, the writer queue's peak, the writer's busy share as
the console's header shows it (median and max of the telemetry while capturing), the telemetry latency a
client sees (receipt time minus the document's sampling time: median and p95), the documents and
JPEGs each client got, the daemon process's CPU seconds per take second (the clients and the load
run in child processes, so their CPU is not counted there), the clients' process's own CPU
seconds per second (`cl CPU`: what a browser tab would cost the same host) and the stop time.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import shutil
import statistics
import tempfile
import threading
import time
import uuid
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import httpx

from rigd.app.config import RigConfig, default_sim_rig
from rigd.app.console.security import TOKEN_HEADER
from rigd.app.console.server import ConsoleServer
from rigd.app.service.daemon import Daemon


@dataclass
class ClientStats:
    docs: int = 0
    jpegs: int = 0
    latencies_s: list[float] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)


def client(url: str, token: str, stop: threading.Event, stats: ClientStats) -> None:
    """A dashboard tab: follow /api/live, fetch each changed preview (latest only, one at a time)."""
    shown: dict[str, int] = {}
    auth = {TOKEN_HEADER: token}
    try:
        with (
            httpx.Client(base_url=url, timeout=10, headers=auth) as http,
            http.stream("GET", "/api/live") as live,
        ):
            event = ""
            for line in live.iter_lines():
                if stop.is_set():
                    return
                if line.startswith("event: "):
                    event = line[7:]
                    continue
                if not line.startswith("data: ") or event != "status":
                    continue
                doc = json.loads(line[6:])
                sampled = datetime.fromisoformat(doc["time_utc"]).timestamp()
                stats.latencies_s.append(time.time() - sampled)
                stats.docs += 1
                for dev, version in doc.get("previews", {}).items():
                    if shown.get(dev) != version:
                        shown[dev] = version
                        if http.get(f"/api/preview/{dev}.jpg").status_code == 200:
                            stats.jpegs += 1
    except httpx.HTTPError as exc:
        if not stop.is_set():
            stats.errors.append(str(exc))


def rig(take_dir: Path, runtime: Path, resolution: tuple[int, int], pixel_format: str) -> RigConfig:
    cfg = default_sim_rig(
        world=f"bench-{uuid.uuid4().hex[:6]}",
        resolution=resolution,
        pixel_format=pixel_format,  # type: ignore[arg-type]
    )
    data = cfg.model_dump(mode="json")
    data["writer"]["disk_reserve_mb"] = 0
    data["service"].update(
        {
            "metrics_port": None,
            "take_dir": str(take_dir),
            "control": f"ipc://{runtime}/control.sock",
            "telemetry": f"ipc://{runtime}/telemetry.sock",
        }
    )
    return RigConfig.from_data(data)


def clients_process(url: str, token: str, n: int, stop: Any, out: Any) -> None:
    """Run `n` clients on threads in this (child) process until `stop`; put their stats in `out`."""
    flag = threading.Event()
    stats = [ClientStats() for _ in range(n)]
    threads = [threading.Thread(target=client, args=(url, token, flag, s), daemon=True) for s in stats]
    for t in threads:
        t.start()
    stop.wait()
    flag.set()
    for t in threads:
        t.join(timeout=15)
    cpu = os.times()
    out.put(([(s.docs, s.jpegs, s.latencies_s, s.errors) for s in stats], cpu.user + cpu.system))


def busy(stop: Any) -> None:
    """Other work on the host: a pure-Python loop at normal priority until `stop`."""
    x = 0
    while not stop.is_set():
        for i in range(100_000):
            x ^= i


def command(daemon: Daemon, cmd: str, args: dict[str, Any]) -> dict[str, Any]:
    reply: dict[str, Any] = json.loads(
        daemon.handle([json.dumps({"v": 1, "cmd": cmd, "args": args}).encode()]) or b"{}"
    )
    if not reply["ok"]:
        raise SystemExit(f"{cmd} refused: {reply['error']}")
    return reply


def run_level(
    daemon: Daemon,
    console: ConsoleServer,
    n_clients: int,
    n_load: int,
    duration_s: float,
    stop_after_s: float | None,
) -> dict[str, Any]:
    """One take with `n_clients` clients and `n_load` busy processes in child processes (their CPU
    is not the daemon's)."""
    mp = multiprocessing.get_context("spawn")
    stop, out = mp.Event(), mp.Queue()
    proc = mp.Process(
        target=clients_process, args=(console.url, console.security.token, n_clients, stop, out), daemon=True
    )
    proc.start()
    hogs = [mp.Process(target=busy, args=(stop,), daemon=True) for _ in range(n_load)]
    for h in hogs:
        h.start()
    time.sleep(3.0)  # let the children start and the clients connect before the take
    cpu0, t0 = os.times(), time.monotonic()
    command(daemon, "capture", {"duration_s": duration_s})
    peak_queue = 0
    busy: list[float] = []
    t_stop: float | None = None
    while True:
        t = daemon.telemetry()
        peak_queue = max(peak_queue, t.queue_depth)
        if t.state == "capturing":
            busy.append(t.writer_busy)
        if t.state == "idle":
            break
        if stop_after_s is not None and t_stop is None and time.monotonic() - t0 >= stop_after_s:
            t_stop = time.monotonic()
            command(daemon, "stop", {})
        time.sleep(0.05)
    wall = time.monotonic() - t0
    stop_s = time.monotonic() - t_stop if t_stop is not None else float("nan")
    cpu1 = os.times()
    load1 = os.getloadavg()[0]
    stop.set()
    per_client, client_cpu = out.get(timeout=60)
    stats = [ClientStats(d, j, lat, err) for d, j, lat, err in per_client]
    proc.join(timeout=15)
    for h in hogs:
        h.join(timeout=15)
    last = t.last_take
    assert last is not None
    lat = sorted(x for s in stats for x in s.latencies_s)
    taken_s = min(duration_s, stop_after_s) if stop_after_s is not None else duration_s
    lost = {"frames": 0, "events": 0}
    for loss in last.losses:
        if loss.what in lost:
            lost[loss.what] += loss.count
    return {
        "load": n_load,
        "loadavg": load1,
        "clients": n_clients,
        "fps": sum(last.frames.values()) / taken_s,
        "eps": sum(last.events.values()) / taken_s,
        "lost_frames": lost["frames"],
        "lost_events": lost["events"],
        "verdict": last.verdict,
        "stop_s": stop_s,
        "peak_queue": peak_queue,
        "busy_med": statistics.median(busy) if busy else float("nan"),
        "busy_max": max(busy, default=float("nan")),
        "lat_med_ms": 1e3 * statistics.median(lat) if lat else float("nan"),
        "lat_p95_ms": 1e3 * lat[int(0.95 * (len(lat) - 1))] if lat else float("nan"),
        "docs_per_client_s": sum(s.docs for s in stats) / max(n_clients, 1) / wall,
        "jpegs_per_client_s": sum(s.jpegs for s in stats) / max(n_clients, 1) / wall,
        "cpu_per_s": ((cpu1.user - cpu0.user) + (cpu1.system - cpu0.system)) / wall,
        "client_cpu_per_s": client_cpu / (wall + 3.0),  # the clients' process, connected 3 s early
        "errors": sum(len(s.errors) for s in stats),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=8.0, help="seconds of each take")
    ap.add_argument(
        "--resolution", default="1280x720", help="sim frame size WIDTHxHEIGHT (default: the default rig's)"
    )
    ap.add_argument("--pixel-format", default="bayer_rg8", choices=["bayer_rg8", "rgb8", "mono8"])
    ap.add_argument("--clients", default="0,1,10", help="client counts to run, comma-separated")
    ap.add_argument("--load", default="0", help="busy background processes per level, comma-separated")
    ap.add_argument("--stop-after", type=float, default=None, help="stop each take after this many seconds")
    args = ap.parse_args()
    w, h = (int(v) for v in args.resolution.split("x"))
    levels = [(int(n), int(c)) for n in args.load.split(",") for c in args.clients.split(",")]
    work = Path(tempfile.mkdtemp(prefix="rigd-bench-console-"))
    os.chmod(work, 0o700)
    try:
        cfg = rig(work / "takes", work, (w, h), args.pixel_format)
        console = ConsoleServer("127.0.0.1", 0)
        daemon = Daemon(cfg, attachments=[console])
        th = threading.Thread(target=daemon.serve, name="bench-daemon", daemon=True)
        th.start()
        if not daemon.wait_ready(60):
            raise SystemExit("daemon did not start")
        rows = []
        for n_load, n_clients in levels:
            rows.append(run_level(daemon, console, n_clients, n_load, args.duration, args.stop_after))
            for f in (work / "takes").glob("*.h5"):  # each take is GBs; keep the disk free
                f.unlink()
        daemon.shutdown()
        th.join(timeout=60)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(
        f"sim rig {w}x{h} {args.pixel_format}, 3 cameras + 2 event sensors at 30 Hz, "
        f"{args.duration:g} s per take, real time, {os.cpu_count()} cores"
    )
    print(
        f"{'load':>4} {'loadavg':>7} {'clients':>7} {'frames/s':>9} {'events/s':>10} {'lost fr':>7} "
        f"{'lost ev':>9} {'verdict':>9} {'queue':>6} {'busy med':>8} {'busy max':>8} "
        f"{'lat med ms':>10} {'lat p95 ms':>10} "
        f"{'docs/s/cl':>9} {'jpeg/s/cl':>9} {'CPU s/s':>7} {'cl CPU':>6} {'stop s':>6} {'errors':>6}"
    )
    for r in rows:
        print(
            f"{r['load']:>4} {r['loadavg']:>7.2f} {r['clients']:>7} {r['fps']:>9.1f} {r['eps']:>10,.0f} "
            f"{r['lost_frames']:>7} {r['lost_events']:>9,} {r['verdict']:>9} {r['peak_queue']:>6} "
            f"{r['busy_med']:>8.0%} {r['busy_max']:>8.0%} "
            f"{r['lat_med_ms']:>10.1f} {r['lat_p95_ms']:>10.1f} {r['docs_per_client_s']:>9.2f} "
            f"{r['jpegs_per_client_s']:>9.1f} {r['cpu_per_s']:>7.2f} "
            f"{r['client_cpu_per_s']:>6.2f} {r['stop_s']:>6.2f} {r['errors']:>6}"
        )


if __name__ == "__main__":
    main()
