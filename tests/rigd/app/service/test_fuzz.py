"""10,000 fuzzed and malformed control messages: every one answered, the daemon still
serving, its memory flat (measured on a daemon in its own process)."""

from __future__ import annotations

import json
import random
from pathlib import Path
from typing import Any

import psutil
import pytest

from rigd.app.service.client import DaemonClient
from rigd.app.service.daemon import Daemon
from rigd.app.service.protocol import Reply
from rigd.app.testing.daemon import endpoints, small_rig, spawn_daemon

N_MESSAGES = 10_000

_SAFE_CMDS = ["ping", "status", "config", "stop"]  # valid forms of these are harmless
_ALL_CMDS = [*_SAFE_CMDS, "capture", "devices", "recover", "shutdown", "fly", "", "PING", "status "]


def _junk_value(rng: random.Random, depth: int = 0) -> Any:
    kind = rng.randrange(9 if depth < 3 else 6)
    if kind == 0:
        return None
    if kind == 1:
        return rng.choice([True, False])
    if kind == 2:
        return rng.choice([0, -1, 1, 2**63, -(2**63), 10**30, 7])
    if kind == 3:
        return rng.choice([0.5, -1e308, 1e-320, 3.0, float("nan")])
    if kind == 4:
        return "".join(chr(rng.randrange(1, 0x2FFF)) for _ in range(rng.randrange(0, 40)))
    if kind == 5:
        return "x" * rng.choice([0, 1, 64, 65, 1000])
    if kind == 6:
        return [_junk_value(rng, depth + 1) for _ in range(rng.randrange(0, 5))]
    return {
        str(_junk_value(rng, depth + 1))[:20]: _junk_value(rng, depth + 1) for _ in range(rng.randrange(0, 5))
    }


def _message(rng: random.Random) -> bytes:
    r = rng.random()
    if r < 0.15:  # random bytes
        return bytes(rng.randrange(256) for _ in range(rng.randrange(0, 200)))
    if r < 0.25:  # truncated / mangled JSON of a valid request
        good = json.dumps({"v": 1, "id": "a", "cmd": rng.choice(_SAFE_CMDS), "args": {}}).encode()
        cut = good[: rng.randrange(len(good))]
        return cut if rng.random() < 0.5 else cut + bytes([rng.randrange(256)]) + good[len(cut) + 1 :]
    if r < 0.35:  # any JSON value
        return json.dumps(_junk_value(rng), allow_nan=True).encode()
    # a request-shaped object with fuzzed fields; never a valid capture/shutdown
    msg: dict[str, Any] = {}
    if rng.random() < 0.9:
        msg["v"] = rng.choice([1, 1, 1, 0, 2, "1", None, 1.0, True])
    if rng.random() < 0.8:
        msg["id"] = rng.choice(["abc", "", "x" * 65, 5, None, "\u2603"])
    cmd = rng.choice(_ALL_CMDS)
    msg["cmd"] = cmd
    if rng.random() < 0.7:
        msg["args"] = rng.choice(
            [
                {},
                _junk_value(rng),
                {"duration_s": rng.choice([-1, 0, "5", None, 1e12])},
                {"force": "yes"},
                {"reason": "r" * 300},
                {"label": "../../etc"},
            ]
        )
    if rng.random() < 0.2:
        msg[str(_junk_value(rng))[:10]] = _junk_value(rng)
    if cmd in ("capture", "shutdown", "recover", "devices"):
        # Keep these from being valid: an unknown argument is always refused.
        args = msg.get("args")
        msg["args"] = {**(args if isinstance(args, dict) else {}), "fuzz_extra": 1}
    body = json.dumps(msg, allow_nan=True).encode()
    if rng.random() < 0.05 and body.startswith(b"{") and len(body) > 2:
        # a key repeated: top level (`"cmd":"shutdown"` last) or nested in args
        dup = rng.choice([b'"cmd":"shutdown",', b'"v":1,', b'"args":{"force":true,"force":true},'])
        body = b"{" + dup + body[1:]
    return body


@pytest.mark.slow
def test_fuzzed_messages_all_answered_daemon_serving_memory_flat(runtime_dir: Path, tmp_path: Path) -> None:
    cfg = small_rig("fuzz", take_dir=str(tmp_path / "takes"))
    proc = spawn_daemon(cfg, runtime_dir, tmp_path / "daemon.log")
    client = DaemonClient(endpoints(runtime_dir)["control"], timeout_s=5.0)
    rng = random.Random(20261121)
    codes: dict[str, int] = {}
    rss: list[int] = []
    ps = psutil.Process(proc.pid)
    try:
        for i in range(N_MESSAGES):
            raw = client.send_raw(_message(rng))  # raises if a message goes unanswered
            reply = Reply.model_validate_json(raw)
            key = "ok" if reply.ok else reply.error.code  # type: ignore[union-attr]
            codes[key] = codes.get(key, 0) + 1
            if i % 1000 == 999:
                rss.append(ps.memory_info().rss)
        assert client.call("ping")["state"] == "idle"
    finally:
        client.close()
        proc.terminate()
        proc.wait(timeout=60)
    print(f"replies by code: {codes}; RSS MB every 1000: {[round(r / 1e6, 1) for r in rss]}")
    assert sum(codes.values()) == N_MESSAGES
    assert codes.get("internal", 0) == 0, codes
    assert {"bad_json", "bad_request", "unknown_command", "unsupported_version"} <= set(codes), codes
    # After warm-up the daemon's memory does not grow with the number of requests.
    growth = max(rss[2:]) - rss[1]
    assert growth < 8e6, [round(r / 1e6, 1) for r in rss]
    assert proc.returncode == 0, (tmp_path / "daemon.log").read_text()[-3000:]


# -- strict types and duplicate keys: answered `bad_request` naming the field, never acted on --

_STRICT_CASES: list[tuple[bytes, str]] = [
    # a string, an int or null is not a bool
    (b'{"v":1,"cmd":"shutdown","args":{"force":"yes"}}', "args.force"),
    (b'{"v":1,"cmd":"shutdown","args":{"force":"true"}}', "args.force"),
    (b'{"v":1,"cmd":"shutdown","args":{"force":1}}', "args.force"),
    (b'{"v":1,"cmd":"shutdown","args":{"force":null}}', "args.force"),
    # the version is an int: not a string, a bool, a float or null
    (b'{"v":"1","cmd":"ping"}', "v"),
    (b'{"v":true,"cmd":"ping"}', "v"),
    (b'{"v":1.0,"cmd":"ping"}', "v"),
    (b'{"v":null,"cmd":"ping"}', "v"),
    (b'{"cmd":"ping"}', "v"),
    # required strings are strings; null is not one
    (b'{"v":1,"cmd":null}', "cmd"),
    (b'{"v":1,"cmd":1}', "cmd"),
    (b'{"v":1,"id":5,"cmd":"ping"}', "id"),
    (b'{"v":1,"cmd":"ping","args":null}', "args"),
    (b'{"v":1,"cmd":"ping","args":[]}', "args"),
    # numbers are numbers, not strings or bools
    (b'{"v":1,"cmd":"capture","args":{"duration_s":"5"}}', "args.duration_s"),
    (b'{"v":1,"cmd":"capture","args":{"duration_s":true}}', "args.duration_s"),
    (b'{"v":1,"cmd":"capture","args":{"label":7}}', "args.label"),
    (b'{"v":1,"cmd":"stop","args":{"reason":false}}', "args.reason"),
    # duplicate keys, at the top and nested; the last one must not win
    (b'{"v":1,"cmd":"ping","cmd":"shutdown"}', "cmd"),
    (b'{"v":1,"v":1,"cmd":"ping"}', "v"),
    (b'{"v":1,"cmd":"shutdown","args":{"force":false,"force":true}}', "args.force"),
    (b'{"v":1,"cmd":"ping","args":{"x":{"y":1,"y":2}}}', "args.x.y"),
    (b'{"v":1,"cmd":"ping","args":{"x":[0,{"y":1,"y":2}]}}', "args.x.1.y"),
    (b'{"v":1,"id":"a","id":"b","cmd":"ping"}', "id"),
]


@pytest.mark.parametrize(("raw", "field"), _STRICT_CASES)
def test_lax_types_and_duplicate_keys_refused_naming_the_field(raw: bytes, field: str) -> None:
    daemon = Daemon(small_rig("strict"), metrics=False)
    try:
        reply = Reply.model_validate_json(daemon.handle([raw]) or b"")
        assert not reply.ok
        assert reply.error is not None
        assert (reply.error.code, reply.error.field) == ("bad_request", field), reply.error
        assert not daemon._stop.is_set(), "a refused request must not shut the daemon down"
    finally:
        daemon._ctx.term()


def test_strict_requests_still_accept_valid_forms() -> None:
    """Strictness is about types, not about refusing what the protocol allows."""
    daemon = Daemon(small_rig("strict-ok"), metrics=False)
    try:
        for raw in (
            b'{"v":1,"cmd":"ping"}',
            b'{"v":1,"id":"x","cmd":"ping","args":{}}',
            b'{"v":1,"cmd":"stop","args":{"reason":"r"}}',  # answered not_capturing, not bad_request
            b'{"v":1,"cmd":"shutdown","args":{"force":false}}',
        ):
            reply = Reply.model_validate_json(daemon.handle([raw]) or b"")
            assert reply.ok or (reply.error is not None and reply.error.code == "not_capturing"), raw
        assert daemon._stop.is_set()  # the last one: a valid shutdown
    finally:
        daemon._ctx.term()
