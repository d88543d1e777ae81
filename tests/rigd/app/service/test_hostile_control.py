"""Hostile input on the control socket: lone surrogates in every string field of every command,
over-long numbers, deep nesting. Every message is answered with a structured error (never
`internal`), and the daemon goes on answering `ping`. Should the control loop die anyway, the
running take is finalized and `rigd serve` exits non-zero; SIGTERM ends a recording daemon."""

from __future__ import annotations

import json
import random
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from rigd.app.config import RigConfig
from rigd.app.service.client import DaemonClient, find_daemon
from rigd.app.service.daemon import ControlPlaneError, Daemon
from rigd.app.service.protocol import ARGS_MODELS, COMMANDS, PROTOCOL_VERSION, Reply
from rigd.app.service.requests import MAX_INT_DIGITS, reply_bytes
from rigd.app.testing.daemon import REPO, RunningDaemon, endpoints, small_rig
from rigd.take.reader import open_take

#: Lone surrogates as JSON escapes (valid JSON, text no encoder can write back).
SURROGATES = ["\\ud800", "\\udbff", "\\udc00", "\\udfff", "\\udc80"]


def surrogate_texts(rng: random.Random) -> Iterator[str]:
    """JSON string bodies holding a lone surrogate: alone, amid text, at either end, a reversed
    pair, a high surrogate followed by a non-surrogate."""
    yield from SURROGATES
    yield "abc" + rng.choice(SURROGATES)
    yield rng.choice(SURROGATES) + "xyz"
    yield "a\\u00e9" + rng.choice(SURROGATES) + "\\u2603b"
    yield "\\udc00\\ud800"  # a pair in the wrong order
    yield "\\ud83dA"  # a high surrogate without its low half


def string_fields(cmd: str) -> list[tuple[str, Callable[[str], str]]]:
    """Every place a string sits in a request for `cmd`, as (field, body maker): the maker takes
    a JSON string body and returns the whole request with it at that place."""

    def req(**parts: str) -> str:
        fields = {"v": str(PROTOCOL_VERSION), "id": '"h"', "cmd": json.dumps(cmd), "args": "{}"}
        fields.update(parts)
        return "{" + ",".join(f'"{k}":{v}' for k, v in fields.items()) + "}"

    out: list[tuple[str, Callable[[str], str]]] = [
        ("id", lambda s: req(id=f'"{s}"')),
        ("cmd", lambda s: req(cmd=f'"{cmd}{s}"')),
        ("<top-level key>", lambda s: req(**{"x": "1"}).replace('"x"', f'"{s}"')),
        ("<top-level value>", lambda s: req(extra=f'"{s}"')),
        ("<args key>", lambda s: req(args=f'{{"{s}":1}}')),
        ("<nested args>", lambda s: req(args=f'{{"deep":[1,{{"k":["{s}"]}}]}}')),
        ("v", lambda s: req(v=f'"{s}"')),
    ]
    for name in ARGS_MODELS[cmd].model_fields:

        def in_args(s: str, n: str = name) -> str:
            return req(args=f'{{"{n}":"{s}"}}')

        out.append((f"args.{name}", in_args))
    return out


def hostile_messages(seed: int = 22) -> list[tuple[str, str, bytes]]:
    """(command, field, message) for every command, string field and surrogate variant."""
    rng = random.Random(seed)
    out = []
    for cmd in COMMANDS:
        for field, make in string_fields(cmd):
            for text in surrogate_texts(rng):
                out.append((cmd, field, make(text).encode()))
    return out


HOSTILE = hostile_messages()


@pytest.fixture(scope="module")
def daemon() -> Iterator[Daemon]:
    """A daemon that is not serving: `handle` is what answers each control message."""
    d = Daemon(small_rig(f"hostile-{uuid.uuid4().hex[:6]}"), metrics=False)
    yield d
    d._ctx.term()


def _reply(raw: bytes | None) -> Reply:
    """A reply as a strict client reads it: UTF-8 and valid JSON."""
    assert raw is not None
    raw.decode("utf-8")  # strict: no surrogates written out
    return Reply.model_validate_json(raw)


def test_every_command_and_string_field_is_covered() -> None:
    covered = {(cmd, field) for cmd, field, _ in HOSTILE}
    for cmd in COMMANDS:
        assert (cmd, "id") in covered
        assert (cmd, "cmd") in covered
        for name in ARGS_MODELS[cmd].model_fields:
            assert (cmd, f"args.{name}") in covered
    assert len(HOSTILE) > 500


@pytest.mark.parametrize("cmd", COMMANDS)
def test_lone_surrogates_in_any_string_field_are_refused_naming_the_field(daemon: Daemon, cmd: str) -> None:
    for _, field, raw in (h for h in HOSTILE if h[0] == cmd):
        reply = _reply(daemon.handle([raw]))
        assert not reply.ok, raw
        assert reply.error is not None
        assert reply.error.code == "bad_request", (raw, reply.error)
        assert "not valid Unicode" in reply.error.message, (raw, reply.error)
        if not field.startswith("<"):
            assert reply.error.field == field, (raw, reply.error)
        assert reply.id is None  # a bad id is never echoed
    assert not daemon._stop.is_set()


json_leaf = st.one_of(
    st.none(), st.booleans(), st.integers(-(10**6), 10**6), st.text(max_size=8), st.floats(allow_nan=False)
)
json_tree = st.recursive(
    json_leaf,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=12,
)


_MARK = "\x01SURROGATE\x01"


def _mark_nth_string(doc: Any, n: int) -> Any:
    """`doc` with `_MARK` appended to its (n mod count)-th string, keys included."""
    count = 0

    def walk(node: Any, mark: int | None) -> Any:
        nonlocal count
        if isinstance(node, str):
            count += 1
            return node + _MARK if count - 1 == mark else node
        if isinstance(node, list):
            return [walk(v, mark) for v in node]
        if isinstance(node, dict):
            return {walk(k, mark): walk(v, mark) for k, v in node.items()}
        return node

    walk(doc, None)
    total = count
    count = 0
    return walk(doc, n % total)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    cmd=st.sampled_from(COMMANDS),
    args=st.dictionaries(st.text(max_size=10), json_tree, max_size=4),
    where=st.integers(0, 10_000),
    surrogate=st.sampled_from(SURROGATES),
)
@pytest.mark.slow
def test_a_lone_surrogate_anywhere_in_any_request_is_refused(
    daemon: Daemon, cmd: str, args: dict[str, Any], where: int, surrogate: str
) -> None:
    """Generated requests with a lone surrogate spliced into one of their strings (a key or a
    value, at any depth): refused `bad_request`, never acted on, never `internal`."""
    doc = _mark_nth_string({"v": 1, "id": "g", "cmd": cmd, "args": args}, where)
    raw = json.dumps(doc).replace(json.dumps(_MARK)[1:-1], surrogate).encode()
    assert surrogate.encode() in raw
    reply = _reply(daemon.handle([raw]))
    assert not reply.ok
    assert reply.error is not None
    assert reply.error.code == "bad_request", (raw, reply.error)
    assert not daemon._stop.is_set()


@pytest.mark.parametrize("digits", [MAX_INT_DIGITS + 1, 300, 4300, 4301, 5000, 20_000])
@pytest.mark.parametrize(
    ("template", "field"),
    [
        ('{{"v":1,"cmd":"capture","args":{{"duration_s":{n}}}}}', "args.duration_s"),
        ('{{"v":1,"cmd":"capture","args":{{"duration_s":-{n}}}}}', "args.duration_s"),
        ('{{"v":{n},"cmd":"ping"}}', "v"),
        ('{{"v":1,"cmd":"shutdown","args":{{"force":{n}}}}}', "args.force"),
        ('{{"v":1,"cmd":"ping","args":{{"x":[1,{{"y":{n}}}]}}}}', "args.x.1.y"),
    ],
)
def test_over_long_numbers_are_refused_naming_the_field(
    daemon: Daemon, digits: int, template: str, field: str
) -> None:
    raw = template.format(n="7" * digits).encode()
    reply = _reply(daemon.handle([raw]))
    assert reply.error is not None
    assert (reply.error.code, reply.error.field) == ("bad_request", field), reply.error


@pytest.mark.parametrize("digits", [400, 5000])
def test_long_floats_are_refused_by_the_bounds_of_their_field(daemon: Daemon, digits: int) -> None:
    raw = ('{"v":1,"cmd":"capture","args":{"duration_s":%s.5}}' % ("9" * digits)).encode()
    reply = _reply(daemon.handle([raw]))
    assert reply.error is not None
    assert (reply.error.code, reply.error.field) == ("bad_request", "args.duration_s"), reply.error


@pytest.mark.parametrize("depth", [1_000, 10_000, 32_000, 100_000])
@pytest.mark.parametrize("opener", ["[", '{"a":'])
def test_deep_nesting_is_refused(daemon: Daemon, depth: int, opener: str) -> None:
    closer = "]" if opener == "[" else "}"
    for raw in (
        (opener * depth + closer * depth).encode(),
        ('{"v":1,"cmd":"ping","args":{"x":' + opener * depth + "1" + closer * depth + "}}").encode(),
    ):
        reply = _reply(daemon.handle([raw]))
        assert reply.error is not None
        assert reply.error.code in ("bad_json", "bad_request"), reply.error


def test_a_reply_that_cannot_be_encoded_is_answered_with_an_error() -> None:
    """A file name that is not UTF-8 comes back from the file system as lone surrogates: the
    reply holding it is answered with a structured error saying where, not a crashed loop."""
    raw = reply_bytes(Reply(id="r1", ok=True, result={"recovered": [{"path": "/takes/\udcff.h5"}]}))
    reply = _reply(raw)
    assert not reply.ok
    assert reply.error is not None
    assert reply.id == "r1"
    assert reply.error.code == "internal"
    assert "result.recovered.0.path" in reply.error.message


def test_handle_never_raises(daemon: Daemon, monkeypatch: pytest.MonkeyPatch) -> None:
    """Even a bug that escapes the request handling is answered, not raised into the loop."""

    def broken(*_: object) -> None:
        raise RuntimeError("a bug")

    monkeypatch.setattr(daemon, "_handle", broken)
    reply = _reply(daemon.handle([b'{"v":1,"cmd":"ping"}']))
    assert reply.error is not None
    assert reply.error.code == "internal"


# -- on a serving daemon --------------------------------------------------------------------


def test_serving_daemon_answers_ping_after_each_hostile_message(start_daemon: Any) -> None:
    """The acceptance test on the socket: each hostile message answered, then a ping answered."""
    rd: RunningDaemon = start_daemon()
    rng = random.Random(7)
    sample = [h for h in HOSTILE if h[1] in ("id", "cmd")] + rng.sample(HOSTILE, 60)
    extra = [
        b'{"v":1,"cmd":"capture","args":{"duration_s":' + b"1" * 5000 + b"}}",
        b"[" * 60_000 + b"]" * 5_000,
        b'{"v":1,"cmd":"ping","id":"\\ud800"}',
    ]
    for raw in [m for _, _, m in sample] + extra:
        reply = _reply(rd.client.send_raw(raw))
        assert not reply.ok
        assert reply.error is not None
        assert reply.error.code in ("bad_request", "bad_json"), (raw[:200], reply.error)
        assert rd.client.call("ping")["state"] == "idle"
    assert not rd.errors


def _wait(cond: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, what
        time.sleep(0.05)


@pytest.mark.slow
def test_a_dead_control_loop_finalizes_the_take_and_ends_serve(
    start_daemon: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Defence in depth: whatever escapes the control loop, the take is finalized (complete) and
    `serve` raises ControlPlaneError, instead of the daemon recording on with no way to stop it."""
    rd: RunningDaemon = start_daemon()
    take = Path(rd.client.call("capture", timeout_s=120)["take"])
    _wait(lambda: rd.client.call("status")["state"] == "capturing", 120, "take did not start")

    def broken(*_: object, **__: object) -> list[bytes]:
        raise RuntimeError("a bug that escapes the loop")

    monkeypatch.setattr(rd.daemon, "handle_frames", broken)  # what the control loop calls
    with pytest.raises(Exception, match="no reply"):
        rd.client.send_raw(b'{"v":1,"cmd":"ping"}', timeout_s=2)
    rd.thread.join(timeout=180)
    assert not rd.thread.is_alive(), "serve() did not end after its control loop died"
    assert len(rd.errors) == 1, rd.errors
    assert isinstance(rd.errors[0], ControlPlaneError), rd.errors
    assert rd.daemon.current_session() is None
    workers = [t for t in threading.enumerate() if t.name.startswith("control-worker")]
    assert not workers, workers  # the failed loop closed its worker pool
    with open_take(take) as t:
        assert t.status == "complete"
        assert "control loop failed" in (t.summary().end_reason or "")


def test_rigd_serve_exits_1_with_one_line_when_its_control_loop_dies(
    runtime_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Exit 1, not 2: the systemd unit restarts on 1 (RestartPreventExitStatus=2 is for config
    errors)."""
    from rigd.app.cli import app

    def broken(self: Daemon, sock: object) -> None:
        raise RuntimeError("a bug that escapes the loop")

    monkeypatch.setattr(Daemon, "_serve_loop", broken)
    monkeypatch.setattr(Daemon, "install_signal_handlers", lambda self: None)  # not in pytest's process
    ep = endpoints(runtime_dir)
    args = ["serve", "--take-dir", str(tmp_path / "takes"), "--control", ep["control"]]
    args += ["--telemetry", ep["telemetry"], "--metrics-port", "-1", "--no-http"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 1, result.output
    # The log has the bug's traceback; the command ends with one line saying what happened.
    last = result.output.strip().splitlines()[-1]
    assert last.startswith("error: the control loop failed (RuntimeError: a bug"), result.output
    assert isinstance(result.exception, SystemExit)  # reported, not raised


def _spawn_with_console_on_any_port(cfg: RigConfig, runtime: Path, log_path: Path) -> subprocess.Popen[bytes]:
    """`rigd serve` in a process of its own, as `spawn_daemon` starts it, but with its console on
    a free port (the default one may be taken on a shared host)."""
    cfg_path = runtime / "rig.json"
    data = cfg.model_dump(mode="json")
    data["service"].update(endpoints(runtime))
    cfg_path.write_text(json.dumps(data))
    with log_path.open("ab") as log:
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "rigd.app.cli",
                "serve",
                "--config",
                str(cfg_path),
                "--http",
                "127.0.0.1:0",
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
            cwd=REPO,
        )
    deadline = time.monotonic() + 120
    while (client := find_daemon(endpoints(runtime)["control"], timeout_s=0.5)) is None:
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise AssertionError(f"daemon did not start: {log_path.read_text()[-2000:]}")
        time.sleep(0.1)
    client.close()
    return proc


@pytest.mark.slow
def test_recording_daemon_survives_a_lone_surrogate_and_stops_on_sigterm(
    runtime_dir: Path, tmp_path: Path
) -> None:
    """The reported scenario, in a process of its own: a take running, `{"cmd":"ping","id":"\\ud800"}`
    sent; the daemon answers it and the next ping, and SIGTERM finalizes the take and ends it."""
    cfg = small_rig("hostile-proc", take_dir=str(tmp_path / "takes"))
    log_path = tmp_path / "daemon.log"
    proc = _spawn_with_console_on_any_port(cfg, runtime_dir, log_path)
    client = DaemonClient(endpoints(runtime_dir)["control"], timeout_s=10.0)
    try:
        take = Path(client.call("capture", timeout_s=120)["take"])
        for raw in (
            b'{"v":1,"cmd":"ping","id":"\\ud800"}',
            b'{"v":1,"cmd":"stop","args":{"reason":"\\udc00"}}',
        ):
            reply = _reply(client.send_raw(raw))
            assert reply.error is not None
            assert reply.error.code == "bad_request"
            assert client.call("ping")["state"] in ("starting", "capturing")
    finally:
        client.close()
        proc.send_signal(signal.SIGTERM)
        try:
            rc = proc.wait(timeout=180)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise AssertionError(f"SIGTERM did not end the daemon: {log_path.read_text()[-3000:]}") from None
    assert rc == 0, log_path.read_text()[-3000:]
    with open_take(take) as t:
        assert t.status == "complete"
