"""A rig split over several daemons on one machine, for tests and `bench.multihost`.

Each host gets its own runtime directory (sockets, 0700), take directory and control endpoint;
with `tcp=True` the control endpoints are loopback TCP ports with CurveZMQ keys (each daemon its
own server key, one client key every daemon authorizes), as hosts on a network would be.
"""

from __future__ import annotations

import socket
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from rigd.app.config import RigConfig

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
