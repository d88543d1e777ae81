"""The ROS 2 acceptance: rigd's MCAP export and bag conversion checked by the ROS consumers' own code.

    python -m bench.ros_acceptance [--work DIR] [--python SCRATCH_PY] [--seconds 2] [--readme]

The consumers (mcap, mcap-ros2-support, rosbags, and the evt3 package as the EVT 3.0 decoder
that is not rigd's) live in a scratch venv outside the project (created under --work when
--python is not given). event_camera_codecs (C++, header-only decoders) is built from a checkout
in step 4, with the EventPacket struct a ROS build would generate standing in for ROS itself.

1. A sim take (3 Bayer cameras, 2 EVT 3.0 sensors, the board scene at 640x360, virtual clock;
   `--readme`: the README's `rigd capture --duration 5` take, the built-in rig at 1280x720)
   exported with `rigd export --format mcap`; the consumer side (bench/consumer_checks/
   ros_check.py) reads every message, decodes the events with evt3 and compares counts, 50 ms
   windows and images with the take (references written here).
2. rosbags-convert's sqlite3 bag of that export converted back with `rigd convert`: identical
   events, trigger edges, frames and pulses.
3. For each EVT 3.0 RAW file in ../shared/data/events: a .db3 bag written by rosbags' Writer
   the way metavision_driver records converts to exactly the events evt3 decodes from the file.
4. With `--codecs DIR --msgs DIR` (checkouts of ros-event-camera/event_camera_codecs and
   event_camera_msgs): event_camera_codecs' own decoders, built here with g++ over a small driver
   program (consumer_checks/event_camera_codecs/decode_packets.cpp), decode every EventPacket of
   the bags the ROS driver recorded for that repository's tests and of the bags of step 3; each
   bag's `rigd convert` take holds exactly those events and trigger edges (sensor time, us).
One PASS/FAIL line per check; exit code 1 if any failed.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import venv
from pathlib import Path

import numpy as np

from rigd.app.capture import run_capture
from rigd.app.config import default_sim_rig
from rigd.app.testing.board import capture_board_take
from rigd.products.convert import convert
from rigd.products.export import ExportOptions, run_export
from rigd.products.ros.bag_convert import sensor_name
from rigd.take.reader import open_take

CHECK = Path(__file__).resolve().parent / "consumer_checks" / "ros_check.py"
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "events"
PACKAGES = ["mcap", "mcap-ros2-support", "rosbags", "evt3", "numpy"]
FAILED: list[str] = []


def check(name: str, ok: bool, detail: str) -> None:
    print(f"{'PASS' if ok else 'FAIL'} {name}: {detail}", flush=True)
    if not ok:
        FAILED.append(name)


def scratch_python(work: Path, given: str | None) -> Path:
    if given:
        return Path(given)
    env = work / "venv"
    py = env / "bin" / "python"
    if not py.exists():
        venv.create(env, with_pip=True)
        subprocess.run([str(py), "-m", "pip", "install", "-q", *PACKAGES], check=True)
    return py


def consumer(py: Path, *args: str) -> None:
    r = subprocess.run([str(py), str(CHECK), *args], capture_output=True, text=True, check=False)
    print(r.stdout, end="", flush=True)
    if r.returncode:
        FAILED.append(f"consumer {args[0]}")
        if r.stderr:
            print(r.stderr[-2000:], flush=True)


def references(take_path: Path, out: Path, messages: int) -> None:
    arrays: dict[str, np.ndarray] = {"messages": np.array(messages)}
    with open_take(take_path) as take:
        arrays["sensors"] = np.array(take.event_sensors)
        arrays["cameras"] = np.array(take.cameras)
        for name in take.event_sensors:
            ev = take.sensor(name).events()
            for k in "xypt":
                arrays[f"{name}/{k}"] = getattr(ev, k)
        for cam in take.cameras:
            fs = take.camera(cam, demosaic=False)
            arrays[f"{cam}/frames"] = np.stack([fs.raw(i) for i in range(len(fs))])
    np.savez(out, **arrays)  # type: ignore[arg-type]


def same_takes(a_path: Path, b_path: Path) -> tuple[bool, str]:
    with open_take(a_path) as a, open_take(b_path) as b:
        notes = []
        ok = sorted(a.event_sensors) == sorted(b.event_sensors) and sorted(a.cameras) == sorted(b.cameras)
        for name in a.event_sensors:
            ea, eb = a.sensor(name).events(), b.sensor(name).events()
            same = len(ea) == len(eb) and all(np.array_equal(getattr(ea, k), getattr(eb, k)) for k in "xypt")
            same &= np.array_equal(a.sensor(name).triggers.t, b.sensor(name).triggers.t)
            notes.append(f"{name} {len(eb)}/{len(ea)} events")
            ok &= same
        for cam in a.cameras:
            fa, fb = a.camera(cam, demosaic=False), b.camera(cam, demosaic=False)
            same = len(fa) == len(fb) and np.array_equal(fa.timestamps_us, fb.timestamps_us)
            same &= all(np.array_equal(fa.raw(i), fb.raw(i)) for i in range(len(fa)))
            notes.append(f"{cam} {len(fb)}/{len(fa)} frames")
            ok &= same
        ok &= np.array_equal(a.pulses().t_us, b.pulses().t_us)
        losses = b.sync_report.losses if b.sync_report else []
        return ok and not losses, ", ".join(notes) + f", {len(losses)} loss records"


def check_with_codecs(codecs: Path, msgs: Path, py: Path, work: Path, bags: list[Path]) -> None:
    """Step 4: event_camera_codecs decodes each bag's EventPackets; `rigd convert` must agree."""
    source = Path(__file__).resolve().parent / "consumer_checks" / "event_camera_codecs"
    decoder = work / "decode_packets"
    cpp = source / "decode_packets.cpp"
    flags = ["-std=c++17", "-O2", f"-I{source}", f"-I{codecs / 'include'}"]
    subprocess.run(["g++", *flags, str(cpp), "-o", str(decoder)], check=True)
    msg = msgs / "msg_ros2" / "EventPacket.msg"
    for bag in bags:
        with (bag / "metadata.yaml").open() as f:
            if "event_camera_msgs/msg/EventPacket" not in f.read():
                print(f"INFO {bag.name}: no event_camera_msgs/EventPacket topic; not a check for this step")
                continue
        ref = work / f"{bag.name}-codecs.npz"
        consumer(py, "ecc", str(bag), str(decoder), str(msg), str(ref))
        want = np.load(ref)
        t_path = work / f"{bag.name}-codecs.h5"
        t_path.unlink(missing_ok=True)
        convert(bag, t_path)
        with open_take(t_path) as t:
            for key in sorted(k.removesuffix("|ev|t") for k in want.files if k.endswith("|ev|t")):
                name = sensor_name(key)
                series = t.sensor(name)
                ev, trig = series.events(), series.triggers
                e = {f: want[f"{key}|ev|{f}"] for f in ("t", "x", "y", "p")}
                g = {f: want[f"{key}|trig|{f}"] for f in ("t", "x", "p")}
                same_ev = len(ev) == e["t"].size and all(
                    np.array_equal(a.astype(np.int64), b.astype(np.int64))
                    for a, b in (
                        (ev.x, e["x"]),
                        (ev.y, e["y"]),
                        (ev.t, e["t"] // 1000),
                        (ev.p > 0, e["p"] > 0),
                    )
                )
                same_trig = len(trig) == g["t"].size and all(
                    np.array_equal(a.astype(np.int64), b.astype(np.int64))
                    for a, b in ((trig.t, g["t"] // 1000), (trig.p, g["p"]), (trig.channel, g["x"]))
                )
                check(
                    f"{bag.name} {key} by event_camera_codecs",
                    same_ev and same_trig,
                    f"{len(ev)} events and {len(trig)} trigger edges in the take; event_camera_codecs "
                    f"decodes {e['t'].size} and {g['t'].size}",
                )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, default=Path("/tmp/rigd-ros-acceptance"))
    ap.add_argument("--python", help="the scratch venv's python (default: a venv made under --work)")
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument(
        "--readme",
        action="store_true",
        help="the README's take: the built-in sim rig (1280x720), not the board",
    )
    ap.add_argument("--codecs", type=Path, help="an event_camera_codecs checkout (step 4)")
    ap.add_argument("--msgs", type=Path, help="an event_camera_msgs checkout (step 4)")
    args = ap.parse_args()
    work: Path = args.work
    work.mkdir(parents=True, exist_ok=True)
    py = scratch_python(work, args.python)

    if args.readme:  # `rigd capture --duration 5 --out takes`: the built-in rig, on virtual time
        rig = default_sim_rig(world="ros-acceptance-readme", clock="virtual")
        take = run_capture(rig, work / "take", args.seconds).path
    else:
        take = capture_board_take(
            work / "take",
            args.seconds,
            (640, 360),
            world="ros-acceptance",
            clock="virtual",
            pixel_format="bayer_rg8",
        ).path
    out = work / "mcap"
    run_export(ExportOptions(take=take, format="mcap", out=out, force=True))
    (mcap,) = out.glob("*.mcap")
    meta = json.loads((out / "export.json").read_text())
    references(take, work / "ref.npz", sum(meta["messages"].values()))
    n_msgs = sum(meta["messages"].values())
    print(f"INFO take {take.name}: exported {mcap.stat().st_size / 1e6:.1f} MB, {n_msgs} messages")
    shutil.rmtree(work / "db3", ignore_errors=True)  # rosbags-convert writes a new bag only
    consumer(py, "export", str(mcap), str(work / "ref.npz"), str(work))

    db3_dir = work / "db3"
    back = work / "back.h5"
    back.unlink(missing_ok=True)
    if db3_dir.is_dir():
        convert(db3_dir, back)
        ok, detail = same_takes(take, back)
        check("rigd convert of rosbags' sqlite3 bag", ok, detail)

    for raw in sorted(DATA.glob("evt3*.raw")) if DATA.is_dir() else []:
        bag = work / f"{raw.stem}-bag"
        shutil.rmtree(bag, ignore_errors=True)
        ref = work / f"{raw.stem}-evt3.npz"
        consumer(py, "rawbag", str(raw), str(bag), str(ref))
        t_path = work / f"{raw.stem}.h5"
        t_path.unlink(missing_ok=True)
        convert(bag, t_path)
        want = np.load(ref)
        with open_take(t_path) as t:
            ev = t.sensor(t.event_sensors[0]).events()
            losses = t.sync_report.losses if t.sync_report else []
        same = len(ev) == want["t"].size and all(
            np.array_equal(a.astype(np.int64), b.astype(np.int64))
            for a, b in ((ev.x, want["x"]), (ev.y, want["y"]), (ev.t, want["t"]), (ev.p > 0, want["p"] > 0))
        )
        check(
            f"{raw.name} driver bag",
            same,
            f"{len(ev)} events from the bag, evt3 decodes {want['t'].size} "
            f"from the file; {len(losses)} loss records",
        )
    if args.codecs is not None and args.msgs is not None:
        driver_bags = sorted(p.parent for p in args.codecs.glob("test/*/*.db3"))
        check_with_codecs(args.codecs, args.msgs, py, work, [*driver_bags, *sorted(work.glob("*-bag"))])
    print("ALL PASS" if not FAILED else f"FAILED: {', '.join(FAILED)}")
    return 1 if FAILED else 0


if __name__ == "__main__":
    sys.exit(main())
