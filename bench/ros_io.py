"""MCAP export and rosbag2 import throughput next to the disk's write rate, and bytes per event.

    python -m bench.ros_io [--take TAKE.h5 | --seconds 10] [--work DIR] [--disk-mb 256]

Without --take, captures a sim take of the default rig (640x360, Bayer cameras, EVT 3.0 event
sensors storing their words, virtual clock) for --seconds. Each step runs in a fresh process
(spawn) so its peak RSS is its own: `rigd export --format mcap`, then `rigd convert` of that MCAP
back to a take. The disk's rate is measured in the same run, dd-style: --disk-mb written in
8 MiB blocks and fdatasync'd, in the work directory. Prints one table.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import resource
import time
from pathlib import Path
from typing import Any

import h5py
from mcap.reader import make_reader


def disk_write_mb_s(d: Path, mb: int) -> float:
    """dd if=/dev/zero bs=8M count=mb/8 conv=fdatasync, in MB/s."""
    block = os.urandom(8 << 20)
    path = d / "dd.bin"
    t = time.perf_counter()
    with path.open("wb") as f:
        for _ in range(max(1, mb // 8)):
            f.write(block)
        f.flush()
        os.fdatasync(f.fileno())
    wall = time.perf_counter() - t
    size = path.stat().st_size
    path.unlink()
    return size / 1e6 / wall


def _export(take: str, out: str, q: Any) -> None:
    from rigd.products.export import ExportOptions, run_export

    t = time.perf_counter()
    run_export(ExportOptions(take=Path(take), format="mcap", out=Path(out), force=True))
    q.put((time.perf_counter() - t, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024))


def _import(src: str, dst: str, q: Any) -> None:
    from rigd.products.convert import convert

    t = time.perf_counter()
    convert(Path(src), Path(dst))
    q.put((time.perf_counter() - t, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024))


def _run(fn: Any, *args: str) -> tuple[float, float]:
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=fn, args=(*args, q))
    p.start()
    out = q.get()
    p.join()
    if p.exitcode:
        raise SystemExit(f"{fn.__name__} failed (exit code {p.exitcode})")
    return out  # type: ignore[no-any-return]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--take", type=Path)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--work", type=Path, default=Path("/tmp/rigd-ros-io"))
    ap.add_argument("--disk-mb", type=int, default=256)
    args = ap.parse_args()
    work: Path = args.work
    work.mkdir(parents=True, exist_ok=True)
    take = args.take
    if take is None:
        from rigd.app.testing.board import capture_board_take

        take = capture_board_take(
            work / "take", args.seconds, (640, 360), world="ros-io", clock="virtual", pixel_format="bayer_rg8"
        ).path
    disk = disk_write_mb_s(work, args.disk_mb)
    out = work / "mcap"
    t_exp, rss_exp = _run(_export, str(take), str(out))
    (mcap,) = out.glob("*.mcap")
    back = work / "back.h5"
    back.unlink(missing_ok=True)
    t_imp, rss_imp = _run(_import, str(mcap), str(back))
    take_mb, mcap_mb = take.stat().st_size / 1e6, mcap.stat().st_size / 1e6
    from rigd.take.reader import open_take

    with open_take(take) as t, h5py.File(take, "r") as f:
        rows = []
        for name in t.event_sensors:
            n = t.sensor(name).count
            g = f[f"events/{name}"]
            stored = sum(g[k].id.get_storage_size() for k in g if isinstance(g[k], h5py.Dataset))
            rows.append((name, n, stored / max(n, 1)))
        dur = sum(len(t.camera(c)) for c in t.cameras)
    meta = json.loads((out / "export.json").read_text())
    print(
        f"take {take.name}: {take_mb:.1f} MB, {dur} frames; "
        f"MCAP {mcap_mb:.1f} MB ({len(meta['messages'])} topics)"
    )
    print(f"{'step':<28}{'wall s':>8}{'MB/s':>10}{'disk MB/s':>11}{'peak RSS MB':>13}")
    print(f"{'disk write (dd, fdatasync)':<28}{'':>8}{disk:>10.0f}{disk:>11.0f}{'':>13}")
    print(f"{'export take -> mcap':<28}{t_exp:>8.2f}{mcap_mb / t_exp:>10.0f}{disk:>11.0f}{rss_exp:>13.0f}")
    print(f"{'convert mcap -> take':<28}{t_imp:>8.2f}{mcap_mb / t_imp:>10.0f}{disk:>11.0f}{rss_imp:>13.0f}")
    print("(MB/s: MCAP bytes written or read per second of the step)")
    print(f"{'sensor':<8}{'events':>12}{'take B/ev':>11}{'MCAP CDR B/ev':>15}")
    for name, n, per in rows:
        with mcap.open("rb") as fh:
            reader = make_reader(fh)
            payload = sum(len(m.data) for _, _, m in reader.iter_messages(topics=[f"/{name}/events"]))
        print(f"{name:<8}{n:>12,}{per:>11.2f}{payload / max(n, 1):>15.2f}")
    print("(take: the sensor's stored datasets, zstd; MCAP: the EventPacket CDR payloads before chunk zstd)")


if __name__ == "__main__":
    main()
