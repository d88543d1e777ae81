"""How fast `rigd takes gather` copies a multi-host take's part from its host's daemon.

    python -m bench.gather [--mb 256] [--repeat 3] [--tcp]

A daemon (the small sim rig, serving in this process's thread) holds a part-sized file of
random bytes in its take directory; the copy runs through its control socket as gather does
(`take_stat` until the host's sha256 is known, `take_read` 4 MiB at a time, three in flight, each
as a binary frame beside the reply, into `.partial`,
sha256 of the copy, rename). Beside it, in the same run: the pieces on their own (the host's
checksum, the reads without the checksums) and the machine's limits for the same bytes: a local
`shutil.copyfile`, hashlib sha256 and a memcpy. The file sits in the page cache (just written):
what is measured is the protocol and checksum cost, not the disk. Medians of `--repeat` runs.
`--tcp`: the daemon listens on TCP loopback instead of its IPC socket (no Curve keys).
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import os
import shutil
import socket
import statistics
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np

from rigd.app.config import HostConfig
from rigd.app.service.client import DaemonClient
from rigd.app.service.daemon import Daemon
from rigd.app.take_gather import BLOCK, default_client, fetch_part, read_block
from rigd.app.testing.daemon import endpoints, serve_in_thread, small_rig

NAME = "bench.B.part.h5"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _new_version(path: Path) -> None:
    """Bump the file's modification time (it must exist): to the daemon, a new version."""
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))


def _median(fn: Callable[[], None], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mb", type=int, default=256, help="Size of the part, MiB.")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--tcp", action="store_true", help="TCP loopback instead of IPC.")
    args = ap.parse_args()
    size = args.mb << 20
    with tempfile.TemporaryDirectory(prefix="rigd-gather-") as tmp:
        work = Path(tmp)
        runtime, host_dir, here = work / "run", work / "host", work / "here"
        runtime.mkdir(mode=0o700)
        host_dir.mkdir()
        here.mkdir()
        data = np.random.default_rng(0).integers(0, 256, size, dtype=np.uint8).tobytes()
        (host_dir / NAME).write_bytes(data)
        ep = endpoints(runtime)
        if args.tcp:
            ep = {
                "control": f"tcp://127.0.0.1:{_free_port()}",
                "telemetry": f"tcp://127.0.0.1:{_free_port()}",
            }
        cfg = small_rig(
            f"gather-{uuid.uuid4().hex[:6]}",
            take_dir=str(host_dir),
            control=ep["control"],
            telemetry=ep["telemetry"],
            recover_on_start=False,  # the part is random bytes, not a take: not to be moved aside
        )
        daemon = Daemon(cfg, metrics=False)
        thread, _ = serve_in_thread(daemon, "bench-daemon")
        host = HostConfig(control=ep["control"])
        try:

            def gather() -> None:
                for p in here.iterdir():
                    p.unlink()
                _new_version(host_dir / NAME)  # the host hashes it again
                fetch_part(default_client(host, 60.0), here / NAME)

            def reads_only() -> None:
                with DaemonClient(host.control, timeout_s=60) as c, (here / "raw").open("wb") as f:
                    for off in range(0, size, BLOCK):
                        f.write(
                            base64.b64decode(
                                c.call("take_read", file=NAME, offset=off, length=BLOCK)["data_b64"]
                            )
                        )

            def reads_binary() -> None:
                with DaemonClient(host.control, timeout_s=60) as c, (here / "raw").open("wb") as f:
                    for off in range(0, size, BLOCK):
                        f.write(read_block(c, NAME, off, BLOCK))

            def host_sha() -> None:
                _new_version(host_dir / NAME)
                with DaemonClient(host.control, timeout_s=60) as c:
                    while c.call("take_stat", file=NAME)["sha256"] is None:
                        time.sleep(0.01)

            assert (host_dir / NAME).stat().st_size == size

            def local_copy() -> None:
                shutil.copyfile(host_dir / NAME, here / "copy")
                os.unlink(here / "copy")

            def sha() -> None:
                hashlib.sha256(data).hexdigest()

            buf = np.empty(size, np.uint8)
            src = np.frombuffer(data, np.uint8)

            def memcpy() -> None:
                np.copyto(buf, src)

            rows = [
                ("rigd takes gather copy (stat + reads + sha256 + rename)", _median(gather, args.repeat)),
                ("  take_read alone (4 MiB requests, base64 in the JSON)", _median(reads_only, args.repeat)),
                ("  take_read alone (4 MiB requests, binary frame)", _median(reads_binary, args.repeat)),
                ("  take_stat alone (host sha256 in its thread)", _median(host_sha, args.repeat)),
                ("machine: shutil.copyfile (page cache)", _median(local_copy, args.repeat)),
                ("machine: hashlib sha256", _median(sha, args.repeat)),
                ("machine: memcpy (np.copyto)", _median(memcpy, args.repeat)),
            ]
        finally:
            daemon.shutdown()
            thread.join(30)
    transport = "TCP loopback" if args.tcp else "IPC"
    print(
        f"gather of a {args.mb} MiB part over {transport}, median of {args.repeat}, "
        f"load {os.getloadavg()[0]:.1f}"
    )
    print("| what | s | MB/s |")
    print("|---|---|---|")
    for what, s in rows:
        print(f"| {what} | {s:.3f} | {size / s / 1e6:,.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
