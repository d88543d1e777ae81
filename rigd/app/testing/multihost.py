"""A rig split over several daemons on one machine, for tests and `bench.multihost`.

Each host gets its own runtime directory (sockets, 0700), take directory and control endpoint;
with `tcp=True` the control endpoints are loopback TCP ports with CurveZMQ keys (each daemon its
own server key, one client key every daemon authorizes), as hosts on a network would be.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rigd.app.config import RigConfig
from rigd.app.service.client import DaemonClient, DaemonUnavailableError

#: The acceptance split: the box and the cameras on A, one event sensor on each of B and C.
DEFAULT_SPLIT: dict[str, tuple[str, ...]] = {
    "A": ("trigger", "cam0", "cam1", "cam2"),
    "B": ("ev0",),
    "C": ("ev1",),
}


@dataclass(frozen=True)
class HostDirs:
    runtime: Path
    takes: Path


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def make_keys(root: Path, hosts: list[str]) -> dict[str, dict[str, str]]:
    """A server key pair per host and one client key pair every host authorizes."""
    import zmq.auth

    keys = root / "keys"
    keys.mkdir(mode=0o700, parents=True, exist_ok=True)
    authorized = keys / "authorized"
    authorized.mkdir(mode=0o700, exist_ok=True)
    client_pub, client_sec = zmq.auth.create_certificates(str(keys), "client")
    (authorized / "client.key").write_bytes(Path(client_pub).read_bytes())
    out: dict[str, dict[str, str]] = {}
    for h in hosts:
        pub, sec = zmq.auth.create_certificates(str(keys), f"server-{h}")
        out[h] = {"public": pub, "secret": sec, "client_secret": client_sec, "authorized": str(authorized)}
    return out


def split_rig(
    base: RigConfig,
    root: Path,
    *,
    split: Mapping[str, tuple[str, ...]] = DEFAULT_SPLIT,
    tcp: bool = False,
    spec_tail: Mapping[str, str] | None = None,
) -> tuple[dict[str, RigConfig], dict[str, HostDirs]]:
    """`base` placed on the hosts of `split`, one config per host (they differ only in
    `service`). `spec_tail` appends query parameters to the sim specs of a host's devices
    (the simulated trigger cable's)."""
    hosts = list(split)
    placed = {dev: h for h, devs in split.items() for dev in devs}
    keys = make_keys(root, hosts) if tcp else {}
    dirs: dict[str, HostDirs] = {}
    table: dict[str, dict[str, object]] = {}
    for h in hosts:
        d = HostDirs(root / h / "run", root / h / "takes")
        d.runtime.mkdir(mode=0o700, parents=True, exist_ok=True)
        d.takes.mkdir(parents=True, exist_ok=True)
        dirs[h] = d
        if tcp:
            table[h] = {
                "control": f"tcp://127.0.0.1:{free_port()}",
                "server_public_key": keys[h]["public"],
                "client_secret_key": keys[h]["client_secret"],
            }
        else:
            table[h] = {"control": f"ipc://{d.runtime}/control.sock"}
    data = base.model_dump(mode="json")
    data["hosts"] = table

    def place(dev: dict[str, object], name: str) -> None:
        if name not in placed:
            raise ValueError(f"split: device {name} is on no host")
        dev["host"] = placed[name]
        tail = (spec_tail or {}).get(placed[name])
        spec = str(dev["spec"])
        if tail and spec.startswith("sim://"):
            dev["spec"] = spec + ("&" if "?" in spec else "?") + tail

    place(data["trigger"], "trigger")
    for dev in [*data["cameras"], *data["event_sensors"]]:
        place(dev, str(dev["name"]))
    configs: dict[str, RigConfig] = {}
    for h in hosts:
        per = {**data, "service": dict(data["service"])}
        per["service"].update(
            host=h,
            control=table[h]["control"],
            telemetry=f"ipc://{dirs[h].runtime}/telemetry.sock",
            take_dir=str(dirs[h].takes),
        )
        if tcp:
            per["service"]["curve"] = {
                "server_secret_key": keys[h]["secret"],
                "authorized_keys_dir": keys[h]["authorized"],
            }
        configs[h] = RigConfig.from_data(per, source=f"split rig, host {h}")
    return configs, dirs


def config_file(config: RigConfig, path: Path) -> Path:
    path.write_text(config.model_dump_json(indent=1))
    return path


def client_for(config: RigConfig, host: str | None = None, timeout_s: float = 10.0) -> DaemonClient:
    """A client of `host`'s daemon (with the rig's Curve keys), or of the config's own daemon."""
    if host is None:
        return DaemonClient(config.service.control_endpoint, timeout_s=timeout_s)
    hc = config.hosts[host]
    return DaemonClient(
        hc.control,
        timeout_s=timeout_s,
        server_public_key=hc.server_public_key,
        client_secret_key=hc.client_secret_key,
    )


def spawn_serve(
    config: RigConfig,
    cfg_path: Path,
    log_path: Path,
    *,
    host: str | None = None,
    env: dict[str, str] | None = None,
    wall_clock_s: float = 0.0,
) -> subprocess.Popen[bytes]:
    """`rigd serve` for `config` in a process of its own, returned once it answers a ping;
    `wall_clock_s`: its wall clock moved by that much (`rigd.app.testing.wall_clock`)."""
    config_file(config, cfg_path)
    cli = ["rigd.app.testing.wall_clock", f"{wall_clock_s:g}"] if wall_clock_s else ["rigd.app.cli"]
    cmd = [sys.executable, "-m", *cli, "serve", "--config", str(cfg_path), "--no-http"]
    cmd += ["--metrics-port", "-1"]
    if host is not None:
        cmd += ["--host", host]
    log = log_path.open("ab")
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env={**os.environ, **(env or {})})
    deadline = time.monotonic() + 120
    client = client_for(config, host, timeout_s=1.0)
    try:
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                tail = log_path.read_text()[-2000:]
                raise RuntimeError(f"rigd serve exited with {proc.returncode}: {tail}")
            try:
                client.call("ping")
                return proc
            except DaemonUnavailableError:
                continue
    finally:
        client.close()
    proc.kill()
    raise RuntimeError(f"rigd serve did not answer in 120 s: {log_path.read_text()[-2000:]}")


def stop_serve(proc: subprocess.Popen[bytes], timeout_s: float = 60.0) -> int:
    """SIGTERM (the daemon finalizes a running take), SIGKILL past `timeout_s`; the exit code."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return int(proc.returncode)


def capture_through(client: DaemonClient, duration_s: float, timeout_s: float = 600.0) -> dict[str, Any]:
    """Ask a daemon for a take and wait until it reports it as its last; that summary."""
    from rigd.app.commands.service import wait_for_take

    res = client.call("capture", timeout_s=120.0, duration_s=duration_s)
    return wait_for_take(client, res["take"], timeout_s=timeout_s, status_timeout_s=30.0)


@dataclass(frozen=True)
class Comparison:
    what: str
    equal: bool
    detail: str


def compare_takes(a: Path, b: Path, *, frames_pixels: bool = True) -> list[Comparison]:
    """Whether two takes hold the same data: events (x, y, p, t), frames (times, pixels),
    pulses, and each device's sync report row."""
    import numpy as np

    from rigd.take import Take

    out: list[Comparison] = []
    with Take(a) as ta, Take(b) as tb:
        pa, pb = ta.pulses(), tb.pulses()
        same = np.array_equal(pa.index, pb.index) and np.array_equal(pa.t_us, pb.t_us)
        out.append(Comparison("pulses", same, f"{len(pa)} vs {len(pb)}"))
        for name in sorted(set(ta.event_sensors) | set(tb.event_sensors)):
            if name not in ta.event_sensors or name not in tb.event_sensors:
                out.append(Comparison(f"events {name}", False, "missing in one take"))
                continue
            ea, eb = ta.sensor(name).events(), tb.sensor(name).events()
            same = len(ea) == len(eb) and all(
                np.array_equal(getattr(ea, c), getattr(eb, c)) for c in ("x", "y", "p", "t")
            )
            out.append(Comparison(f"events {name}", same, f"{len(ea):,} vs {len(eb):,}"))
        for name in sorted(set(ta.cameras) | set(tb.cameras)):
            if name not in ta.cameras or name not in tb.cameras:
                out.append(Comparison(f"frames {name}", False, "missing in one take"))
                continue
            fa, fb = ta.camera(name), tb.camera(name)
            same = np.array_equal(fa.timestamps_us, fb.timestamps_us)
            if same and frames_pixels:
                same = all(np.array_equal(fa.raw(i), fb.raw(i)) for i in range(len(fa)))
            out.append(Comparison(f"frames {name}", same, f"{len(fa)} vs {len(fb)}"))
        ra, rb = ta.sync_report, tb.sync_report
        for name in sorted(set(ra.devices if ra else {}) | set(rb.devices if rb else {})):
            da = ra.devices.get(name) if ra else None
            db = rb.devices.get(name) if rb else None
            same = da is not None and db is not None and da.model_dump() == db.model_dump()
            out.append(Comparison(f"sync {name}", same, "" if same else f"{da} vs {db}"))
        same = (
            ra is not None
            and rb is not None
            and (ra.n_pulses, ra.t_first_pulse_us, ra.losses)
            == (
                rb.n_pulses,
                rb.t_first_pulse_us,
                rb.losses,
            )
        )
        out.append(Comparison("sync report", same, ""))
    return out
