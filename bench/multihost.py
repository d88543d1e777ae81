"""One rig over several daemons: the split take against the single-daemon take of the same config.

    python -m bench.multihost --hosts 3 --sim-clock virtual --duration 3 --out DIR
    python -m bench.multihost --hosts 3 --sim-clock real --duration 5 --resolution 1280x720 --out DIR

Starts the daemons itself (`rigd serve --host H`, each with its own runtime and take directory,
control on loopback TCP with CurveZMQ keys), the simulated trigger cable carrying the box's wire
from host A's world to the others, captures the split take through host A, then stops them and
captures the same config through one daemon. Both land in DIR: `split.h5` with its part files
beside it, `single.h5`. Prints what each take holds side by side (verdict, events, frames,
the aggregate events/s and MB/s written over the take's duration, the wall time from the request
to the sealed take, each daemon's CPU seconds; beside them the machine's cores and its disk's
write MB/s measured in DIR), and whether events, frames, pulses and
sync report are equal (on the virtual clock they must be; `--threshold` lowers the sensors'
contrast threshold for more events per second).
Every process it started is stopped (SIGTERM, then SIGKILL) however the run ends.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Literal

from bench.capacity_device import disk_write_mbs
from firmware_sim.cable import cable_params
from rigd.app.config import default_sim_rig
from rigd.app.testing.multihost import (
    capture_through,
    client_for,
    compare_takes,
    spawn_serve,
    split_rig,
    stop_serve,
)

SPLITS: dict[int, dict[str, tuple[str, ...]]] = {
    1: {"A": ("trigger", "cam0", "cam1", "cam2", "ev0", "ev1")},
    2: {"A": ("trigger", "cam0", "cam1", "cam2"), "B": ("ev0", "ev1")},
    3: {"A": ("trigger", "cam0", "cam1", "cam2"), "B": ("ev0",), "C": ("ev1",)},
}


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process and its threads (/proc), 0 when it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run(args: argparse.Namespace) -> int:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    clock: Literal["real", "virtual"] = args.sim_clock
    w, h = (int(v) for v in args.resolution.split("x"))
    root = Path(tempfile.mkdtemp(prefix="rigd-multihost-"))
    root.chmod(0o700)
    split = SPLITS[args.hosts]
    followers = len(split) - 1
    cable = root / "cable" / "wire.sock"
    cable.parent.mkdir(mode=0o700)
    tails = {host: cable_params(cable, "follow") for host in split}
    tails["A"] = cable_params(cable, "lead", followers)
    base = default_sim_rig(world="bench-multihost", resolution=(w, h), clock=clock)
    data = base.model_dump(mode="json")
    if args.threshold is not None:  # the sim sensors' contrast threshold: lower, more events
        for sen in data["event_sensors"]:
            sen["spec"] += f"&threshold={args.threshold:g}"
    data["writer"]["disk_reserve_mb"] = 0
    data["service"]["metrics_port"] = None
    configs, _dirs = split_rig(
        base.model_validate(data),
        root / "split",
        split=split,
        tcp=True,
        spec_tail=tails if followers else None,
    )
    procs: dict[str, subprocess.Popen[bytes]] = {}
    rows: list[tuple[str, str, str]] = []
    try:
        for host in reversed(list(split)):  # followers first: the lead's clock waits for them
            procs[host] = spawn_serve(configs[host], root / f"{host}.json", root / f"{host}.log", host=host)
        cpu0 = {host: cpu_s(p.pid) for host, p in procs.items()}
        client = client_for(configs["A"], "A", timeout_s=30)
        t0 = time.monotonic()
        split_last = capture_through(client, args.duration)
        split_wall = time.monotonic() - t0
        client.close()
        split_cpu = {host: cpu_s(p.pid) - cpu0[host] for host, p in procs.items()}
        for p in procs.values():
            stop_serve(p)
        procs.clear()
        joined = Path(split_last["path"])
        split_bytes = 0
        for part in joined.parent.glob(f"{joined.stem}.*.part.h5"):
            shutil.copy2(part, out / part.name)
            split_bytes += part.stat().st_size
        shutil.copy2(joined, out / "split.h5")
        split_bytes += joined.stat().st_size

        single_cfg = base.model_validate(
            {**data, "service": {**data["service"], "take_dir": str(root / "single" / "takes")}}
        )
        run_dir = root / "single" / "run"
        run_dir.mkdir(mode=0o700, parents=True)
        single_cfg = single_cfg.model_validate(
            {
                **single_cfg.model_dump(mode="json"),
                "service": {
                    **single_cfg.model_dump(mode="json")["service"],
                    "control": f"ipc://{run_dir}/control.sock",
                    "telemetry": f"ipc://{run_dir}/telemetry.sock",
                },
            }
        )
        procs["single"] = spawn_serve(single_cfg, root / "single.json", root / "single.log")
        c0 = cpu_s(procs["single"].pid)
        client = client_for(single_cfg)
        t0 = time.monotonic()
        single_last = capture_through(client, args.duration)
        single_wall = time.monotonic() - t0
        client.close()
        single_cpu = cpu_s(procs["single"].pid) - c0
        stop_serve(procs.pop("single"))
        shutil.copy2(single_last["path"], out / "single.h5")
    finally:
        for p in procs.values():
            stop_serve(p)
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)

    def events(last: dict[str, object]) -> int:
        ev = last.get("events") or {}
        assert isinstance(ev, dict)
        return sum(int(v) for v in ev.values())

    disk = disk_write_mbs(out, 256)
    print(
        f"machine: {os.cpu_count()} cores, disk {disk:.0f} MB/s (256 MiB written and fsynced in DIR); "
        f"{args.hosts} host(s) on it; clock={clock}; {w}x{h}; {args.duration:g} s"
    )
    print(
        f"{'take':<8} {'verdict':<10} {'events':>12} {'frames':>7} {'wall s':>7} {'Mev/s':>7} {'MB/s':>7}  "
        "CPU s by daemon"
    )
    single_bytes = (out / "single.h5").stat().st_size
    for name, last, wall, cpu, nbytes in (
        ("split", split_last, split_wall, split_cpu, split_bytes),
        ("single", single_last, single_wall, {"single": single_cpu}, single_bytes),
    ):
        fr = last.get("frames") or {}
        assert isinstance(fr, dict)
        n_ev = events(last)
        cpus = ", ".join(f"{k} {v:.1f}" for k, v in cpu.items())
        print(
            f"{name:<8} {last.get('verdict')!s:<10} {n_ev:>12,} {sum(fr.values()):>7} {wall:>7.1f} "
            f"{n_ev / args.duration / 1e6:>7.2f} {nbytes / args.duration / 1e6:>7.1f}  {cpus}"
        )
    for name, last in (("split", split_last), ("single", single_last)):
        for why in (last.get("verdict_reasons") or [])[:6]:
            print(f"  {name}: {why}")
    print()
    diffs = compare_takes(out / "split.h5", out / "single.h5")
    print(f"{'split.h5 vs single.h5':<24} equal  detail")
    for d in diffs:
        rows.append((d.what, "yes" if d.equal else "NO", d.detail))
        print(f"{d.what:<24} {'yes' if d.equal else 'NO':<6} {d.detail[:90]}")
    equal = all(d.equal for d in diffs)
    print(f"\nwritten: {out / 'split.h5'} (+ parts), {out / 'single.h5'}")
    if clock == "virtual" and not equal:
        print("FAIL: on the virtual clock the split take must equal the single-daemon take")
        return 1
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--hosts", type=int, choices=sorted(SPLITS), default=3)
    p.add_argument("--sim-clock", choices=("real", "virtual"), default="virtual")
    p.add_argument("--duration", type=float, default=3.0)
    p.add_argument(
        "--resolution", default="320x240", help="Cameras and sensors, WxH (default rig: 1280x720)."
    )
    p.add_argument("--threshold", type=float, default=None, help="Event sensors' contrast threshold (0.3).")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--keep", action="store_true", help="Keep the daemons' directories and logs.")
    return run(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
