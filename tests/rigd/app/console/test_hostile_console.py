"""Hostile input on the web console: lone surrogates in every body field, path and query of every
route; bodies too big (with and without Content-Length); symlinks in take_dir and its calibration
directory; duplicate keys; deep nesting, over-long numbers and names. Every request is answered
with a 4xx naming what is wrong (never a 500), nothing is read or written through a link, and
the daemon goes on answering `ping` on its control socket."""

from __future__ import annotations

import json
import os
import random
import select
import shutil
import socket
import tempfile
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote

import httpx
import psutil
import pytest
from pydantic import BaseModel

from rigd.app.capture import run_capture
from rigd.app.config import RigConfig, default_sim_rig
from rigd.app.console import app as console_app
from rigd.app.console import calibrate
from rigd.app.console.security import TOKEN_HEADER
from rigd.app.console.server import ConsoleServer
from rigd.app.console.takes import TakeList
from rigd.app.service.client import DaemonClient
from rigd.app.service.daemon import Daemon
from rigd.app.testing.console import console_rig
from rigd.app.testing.daemon import serve_in_thread
from rigd.core.errors import RigdError

#: The body limit (the control socket's message limit).
LIMIT = 64 * 1024
SURROGATES = ["\\ud800", "\\udbff", "\\udc00", "\\udfff", "\\udc80"]

#: Every console route that takes a JSON body, and the model of that body.
BODY_ROUTES: dict[str, type[BaseModel]] = {
    "/api/event-window": console_app.WindowBody,
    "/api/takes/start": console_app.StartBody,
    "/api/takes/stop": console_app.StopBody,
    "/api/guided/start": calibrate.GuidedStartBody,
    "/api/guided/drop": calibrate.DropBody,
    "/api/guided/finish": calibrate.FinishBody,
    "/api/guided/cancel": BaseModel,
}


@dataclass
class Served:
    daemon: Daemon
    console: ConsoleServer
    config: RigConfig
    http: httpx.Client
    client: DaemonClient

    @property
    def take_dir(self) -> Path:
        return self.config.service.take_dir

    def alive(self) -> None:
        """The control socket answers ping, the console its status, and no take was started."""
        assert self.client.call("ping")["state"] == "idle"
        r = self.http.get("/api/status")
        assert r.status_code == 200, r.text
        assert r.json()["state"] == "idle"


def auth_headers(console: ConsoleServer) -> dict[str, str]:
    """What a state-changing request needs besides its JSON body (the console's token)."""
    return {TOKEN_HEADER: console.security.token}


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    """One daemon with its console for the module (most tests only send requests it refuses)."""
    runtime = Path(tempfile.mkdtemp(prefix="rigd-h-"))
    os.chmod(runtime, 0o700)
    cfg = console_rig(tmp_path_factory.mktemp("hostile") / "takes", runtime)
    console = ConsoleServer("127.0.0.1", 0)
    daemon = Daemon(cfg, attachments=[console])
    thread, errors = serve_in_thread(daemon, "hostile-console")
    base = console.url.rstrip("/")
    http = httpx.Client(base_url=base, timeout=60, headers=auth_headers(console))
    client = DaemonClient(cfg.service.control_endpoint, timeout_s=30)
    try:
        yield Served(daemon, console, cfg, http, client)
    finally:
        http.close()
        client.close()
        daemon.shutdown()
        thread.join(timeout=60)
        shutil.rmtree(runtime, ignore_errors=True)
    assert not errors, errors


def post_raw(s: Served, route: str, body: str | bytes) -> httpx.Response:
    raw = body.encode() if isinstance(body, str) else body
    return s.http.post(route, content=raw, headers={"Content-Type": "application/json"})


def refused(r: httpx.Response, status: int = 400) -> dict[str, Any]:
    assert r.status_code == status, (r.status_code, r.text[:300])
    r.content.decode("utf-8")  # strict UTF-8 out
    error = r.json()["error"]
    assert isinstance(error, dict)
    return error


# -- lone surrogates --------------------------------------------------------------------------


def surrogate_bodies(model: type[BaseModel], rng: random.Random) -> Iterator[tuple[str, str]]:
    """(field, body) with a lone surrogate at each place a string can sit in `model`'s body."""
    for name in model.model_fields:
        for s in SURROGATES:
            yield name, f'{{"{name}":"{s}"}}'
        yield name, f'{{"{name}":"ok{rng.choice(SURROGATES)}ok"}}'
        yield f"{name}.0", f'{{"{name}":["{rng.choice(SURROGATES)}"]}}'
        yield f"{name}.k", f'{{"{name}":{{"k":"\\udc00\\ud800"}}}}'
    for s in SURROGATES:
        yield "", f'{{"{s}":1}}'
        yield "extra", f'{{"extra":"a{s}"}}'


def test_every_body_route_and_field_is_covered() -> None:
    from rigd.app.console.calibrate import CancelBody  # the cancel route reads its body too

    assert not CancelBody.model_fields
    for route, model in BODY_ROUTES.items():
        fields = {f.split(".")[0] for f, _ in surrogate_bodies(model, random.Random(0))}
        assert set(model.model_fields) <= fields, route


@pytest.mark.parametrize("route", list(BODY_ROUTES))
def test_lone_surrogates_in_any_body_field_are_refused_and_ping_answers(served: Served, route: str) -> None:
    rng = random.Random(route)
    for field, body in surrogate_bodies(BODY_ROUTES[route], rng):
        error = refused(post_raw(served, route, body))
        assert error["code"] == "bad_request", (body, error)
        assert "not valid Unicode" in error["message"], (body, error)
        if field:
            assert error["field"] == field, (body, error)
        served.alive()


#: Raw (already percent-encoded) path and query pieces: UTF-8 of surrogates, broken UTF-8,
#: a backslash escape, NUL, traversal.
RAW_PIECES = [
    "%ED%A0%80",
    "%ED%B0%80",
    "a%ED%BF%BFb",
    "%F0%9F",
    "%FF%FE",
    "%C0%AF",
    "%5Cud800",
    "%00",
    "..%2F..%2Fetc",
]
PATH_TEMPLATES = [
    "/api/preview/{x}.jpg",
    "/api/takes/{x}/rates",
    "/api/takes/{x}.h5/rates",
    "/api/takes/{x}.h5/preview/cam0.jpg",
    "/api/takes/a.h5/preview/{x}.jpg",
    "/api/guided/files/{x}",
    "/api/guided/files/{x}.yaml",
    "/?token={x}",
    "/calibrate?token={x}",
    "/api/status?{x}={x}",
    "/api/takes?running={x}",
    "/static/{x}",
]


@pytest.mark.parametrize("template", PATH_TEMPLATES)
def test_lone_surrogates_and_broken_utf8_in_paths_and_queries(served: Served, template: str) -> None:
    for piece in RAW_PIECES:
        r = served.http.get(template.format(x=piece))
        assert r.status_code < 500, (template, piece, r.status_code, r.text[:300])
        served.alive()


# -- body size --------------------------------------------------------------------------------


def _raw_request(s: Served, head: str) -> socket.socket:
    host, port = "127.0.0.1", s.console.port
    sock = socket.create_connection((host, port), timeout=60)
    token = s.console.security.token
    sock.sendall(
        (
            f"{head}\r\nHost: {host}:{port}\r\nContent-Type: application/json\r\n{TOKEN_HEADER}: {token}\r\n"
        ).encode()
    )
    return sock


def _status_of(sock: socket.socket) -> int:
    data = b""
    while b"\r\n" not in data:
        chunk = sock.recv(4096)
        if not chunk:
            break
        data += chunk
    return int(data.split(b" ", 2)[1])


def _send_until_answered(sock: socket.socket, total: int, chunked: bool) -> tuple[int, int]:
    """Send up to `total` body bytes (64 KiB pieces) until the server answers; (status, sent)."""
    piece = b"[" * 65536
    sent = 0
    while sent < total:
        readable, _, _ = select.select([sock], [], [], 0)
        if readable:
            break
        try:
            sock.sendall(b"10000\r\n" + piece + b"\r\n" if chunked else piece)
        except (BrokenPipeError, ConnectionResetError):
            break
        sent += len(piece)
    if sent >= total and chunked:
        sock.sendall(b"0\r\n\r\n")
    return _status_of(sock), sent


@pytest.mark.parametrize("route", ["/api/takes/start", "/api/guided/finish", "/api/guided/cancel"])
def test_a_declared_huge_body_is_refused_before_it_is_sent(served: Served, route: str) -> None:
    for length in (LIMIT + 1, 100_000_000, 10**18):
        with _raw_request(served, f"POST {route} HTTP/1.1") as sock:
            sock.sendall(f"Content-Length: {length}\r\n\r\n".encode())
            sock.sendall(b"{" * 1000)
            assert _status_of(sock) == 413  # answered without the rest of the body
    served.alive()


def test_big_bodies_are_refused_413_and_memory_stays_flat(served: Served) -> None:
    """Four 100 MB bodies, chunked (no Content-Length) and declared: each refused 413 long
    before it is all sent, and the process does not grow by what was sent."""
    proc = psutil.Process()
    rss0 = proc.memory_info().rss
    for i in range(4):
        with _raw_request(served, "POST /api/takes/start HTTP/1.1") as sock:
            if i % 2 == 0:
                sock.sendall(b"Transfer-Encoding: chunked\r\n\r\n")
            else:
                sock.sendall(b"Content-Length: 100000000\r\n\r\n")
            status, sent = _send_until_answered(sock, 100_000_000, chunked=i % 2 == 0)
        assert status == 413
        assert sent < 50_000_000, sent
    growth = proc.memory_info().rss - rss0
    assert growth < 100e6, f"RSS grew {growth / 1e6:.0f} MB"
    served.alive()


def test_a_legitimate_body_fits_the_limit(served: Served) -> None:
    """The biggest body the console's pages send: 4000 characters of notes, each an escaped
    emoji (12 bytes). It is read (and refused for its label, so no take starts), not 413."""
    notes = "\\ud83d\\ude00" * 4000
    body = f'{{"label":"bad label!","notes":"{notes}"}}'
    assert len(body) < LIMIT
    error = refused(post_raw(served, "/api/takes/start", body))
    assert error["field"] == "args.label"
    served.alive()


# -- duplicate keys, deep nesting, long numbers and names --------------------------------------


@pytest.mark.parametrize("route", [r for r, m in BODY_ROUTES.items() if m.model_fields])
def test_duplicate_keys_are_refused_like_on_the_control_socket(served: Served, route: str) -> None:
    for name in BODY_ROUTES[route].model_fields:
        for body, field in (
            (f'{{"{name}":1,"{name}":2}}', name),
            (f'{{"{name}":"a","{name}":null}}', name),
            (f'{{"{name}":{{"k":1,"k":1}}}}', f"{name}.k"),
            (f'{{"{name}":[0,{{"k":1,"k":2}}]}}', f"{name}.1.k"),
        ):
            error = refused(post_raw(served, route, body))
            assert (error["code"], error["field"]) == ("bad_request", field), (body, error)
    # The last value must not win: this would otherwise start a take of 1 s.
    refused(post_raw(served, "/api/takes/start", '{"duration_s":-1,"duration_s":1}'))
    served.alive()
    assert not list(served.take_dir.glob("*.h5"))


@pytest.mark.parametrize("route", list(BODY_ROUTES))
def test_deep_nesting_is_a_4xx(served: Served, route: str) -> None:
    for opener, closer in (("[", "]"), ('{"a":', "}")):
        for depth in (1_000, 5_000, 100_000):
            for body in (
                opener * depth + "1" + closer * depth,
                '{"x":' + opener * depth + "1" + closer * depth + "}",
            ):
                r = post_raw(served, route, body)
                assert r.status_code in (400, 413), (route, depth, r.status_code, r.text[:200])
                if len(body) <= LIMIT:
                    assert r.status_code == 400
    served.alive()


@pytest.mark.parametrize("digits", [65, 300, 4300, 4301, 5000, 20_000])
def test_over_long_numbers_are_a_400_naming_the_field(served: Served, digits: int) -> None:
    n = "7" * digits
    for route, name in (
        ("/api/takes/start", "duration_s"),
        ("/api/event-window", "window_ms"),
        ("/api/guided/drop", "index"),
        ("/api/guided/start", "min_views"),
    ):
        error = refused(post_raw(served, route, f'{{"{name}":{n}}}'))
        assert error["field"] == name, (route, error)
    # through the console to the control protocol: a long float is refused by its bounds
    error = refused(post_raw(served, "/api/takes/start", f'{{"duration_s":{n}.5}}'))
    assert error["field"] == "args.duration_s"
    served.alive()


def long_names() -> Iterator[str]:
    for n in (201, 255, 256, 300, 1000):
        for ch in ("a", "\u00e9", "\U0001f600"):
            yield ch * n
            yield ch * (n - 3) + ".h5"


@pytest.mark.parametrize(
    "template",
    [
        "/api/takes/{x}/rates",
        "/api/takes/{x}/preview/cam0.jpg",
        "/api/takes/t.h5/preview/{x}.jpg",
        "/api/guided/files/{x}",
        "/api/preview/{x}.jpg",
    ],
)
def test_long_names_on_routes_are_a_4xx(served: Served, template: str) -> None:
    for name in long_names():
        r = served.http.get(template.format(x=quote(name)))
        assert 400 <= r.status_code < 500, (template, len(name), r.status_code, r.text[:200])
        if "{x}/" in template or template.endswith("{x}"):  # a take or file name: said to be too long
            assert "the limit is 200" in r.json()["error"]["message"], r.text[:300]
    for name in long_names():
        error = refused(post_raw(served, "/api/guided/finish", json.dumps({"into_take": name})))
        assert error["field"] == "into_take"
        error = refused(post_raw(served, "/api/takes/start", json.dumps({"label": name})))
        assert error["field"] == "args.label"
    served.alive()


# -- symlinks -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def outside_take(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real take, outside the console's take_dir."""
    out = tmp_path_factory.mktemp("outside")
    cfg = default_sim_rig(world=f"ho-{uuid.uuid4().hex[:6]}", resolution=(64, 48), clock="virtual")
    data = cfg.model_dump(mode="json")
    data["writer"]["disk_reserve_mb"] = 0
    data["writer"]["disk_ballast_mb"] = 24  # the minimum for this rig is about 20
    return run_capture(RigConfig.from_data(data), out, 0.5).path


@pytest.mark.slow
def test_symlinks_in_take_dir_and_calibration_are_never_followed(
    served: Served, outside_take: Path, tmp_path: Path
) -> None:
    take_dir = served.take_dir
    calib = take_dir / "calibration"
    secret = tmp_path / "secret.txt"
    secret.write_text("root:x:0:0:secret\n")
    planted = [
        take_dir / "passwd.h5",
        take_dir / "outside.h5",
        take_dir / "inside.h5",
        take_dir / f"inside.h5{console_app.NOTES_SUFFIX}",
    ]
    try:
        planted[0].symlink_to(secret)
        planted[1].symlink_to(outside_take)
        shutil.copyfile(outside_take, planted[2])
        planted[3].symlink_to(secret)
        calib.mkdir(exist_ok=True)
        (calib / "cam0-x.yaml").symlink_to(secret)
        (calib / "good.yaml").write_text("k: 1\n")

        listing = served.http.get("/api/takes").json()["takes"]
        assert [e["name"] for e in listing] == ["inside.h5"]
        assert "secret" not in json.dumps(listing)
        assert listing[0]["notes"].startswith("(notes not read")
        for path in (
            "/api/takes/passwd.h5/rates",
            "/api/takes/outside.h5/rates",
            "/api/takes/outside.h5/preview/cam0.jpg",
            "/api/guided/files/cam0-x.yaml",
        ):
            error = refused(served.http.get(path), 404)
            assert "symbolic link" in error["message"], (path, error)
        assert served.http.get("/api/takes/inside.h5/rates").status_code == 200
        assert served.http.get("/api/guided/files/good.yaml").text == "k: 1\n"

        # The calibration directory itself a link: nothing served from it, nothing written to it.
        elsewhere = tmp_path / "elsewhere"
        shutil.move(calib, elsewhere)
        calib.symlink_to(elsewhere)
        error = refused(served.http.get("/api/guided/files/good.yaml"), 404)
        assert "symbolic link" in error["message"]
        before = sorted(p.name for p in elsewhere.iterdir())
        error = refused(post_raw(served, "/api/guided/start", '{"camera":"cam0"}'), 409)
        assert "symbolic link" in error["message"]
        assert sorted(p.name for p in elsewhere.iterdir()) == before
        served.alive()
    finally:
        for p in [*planted, calib]:
            if p.is_symlink() or p.is_file():
                p.unlink()
        shutil.rmtree(calib, ignore_errors=True)


def test_take_names_are_plain_files_of_take_dir(tmp_path: Path, outside_take: Path) -> None:
    takes = TakeList(tmp_path)
    (tmp_path / "link.h5").symlink_to(outside_take)
    (tmp_path / "dir.h5").mkdir()
    for name in (
        "link.h5",
        "dir.h5",
        "../x.h5",
        "a/b.h5",
        ".h.h5",
        "x\x00.h5",
        "\udcff.h5",
        "a" * 300 + ".h5",
    ):
        with pytest.raises(RigdError):
            takes.path_of(name)
    assert takes.entries() == []


def test_notes_are_never_written_through_a_link(tmp_path: Path) -> None:
    target = tmp_path / "target.txt"
    target.write_text("keep me")
    take = tmp_path / "t.h5"
    (tmp_path / f"t.h5{console_app.NOTES_SUFFIX}").symlink_to(target)
    with pytest.raises(OSError, match="symbolic links"):  # ELOOP: Too many levels of symbolic links
        console_app._write_notes(take, "overwritten?")
    assert target.read_text() == "keep me"
    # a FIFO planted where the notes go: refused at once, not a write that blocks forever
    fifo_take = tmp_path / "f.h5"
    os.mkfifo(tmp_path / f"f.h5{console_app.NOTES_SUFFIX}")
    with pytest.raises(OSError, match="No such device"):  # ENXIO: no reader, O_NONBLOCK
        console_app._write_notes(fifo_take, "x")
    assert (
        console_app._read_notes(fifo_take)
        == f"(notes not read: {tmp_path}/f.h5.notes.txt is not a regular file)"
    )


def test_calibration_results_are_never_written_through_a_link(tmp_path: Path) -> None:
    refuse_links = calibrate._refuse_links  # type: ignore[attr-defined]
    target = tmp_path / "target.yaml"
    (tmp_path / "cam0.yaml").symlink_to(target)
    with pytest.raises(RigdError, match="symbolic link"):
        refuse_links(tmp_path / "cam0.yaml", None)
    refuse_links(tmp_path / "fresh.yaml", None)  # a plain new file is fine
    assert not target.exists()


def test_the_hostile_suite_left_the_daemon_serving(served: Served) -> None:
    """Last: after everything above, the same daemon still answers and recorded nothing."""
    served.alive()
    assert served.client.call("ping")["pid"] == os.getpid()
    assert not list(served.take_dir.glob("*.h5"))
