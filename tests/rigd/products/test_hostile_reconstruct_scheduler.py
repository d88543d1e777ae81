"""`rigd reconstruct --scheduler` against bad values and a scheduler that is not there: one line
naming the flag and the accepted forms, no traceback, no output directory, the take unchanged;
an unreachable address fails after a short connect timeout instead of dask's 30 s."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError
from typer.testing import CliRunner

from firmware_sim.testing.takes import make_take
from rigd.app.cli import app
from rigd.products import reconstruct_scheduler
from rigd.products.reconstruct_options import ReconstructOptions

runner = CliRunner()

BAD = [
    "bogus",
    "thread",
    "Threads",
    "",
    " ",
    "threads ",
    "nan",
    "-1",
    "tcp://",
    "tcp://host",
    "tcp://127.0.0.1:",
    "tcp://127.0.0.1:0",
    "tcp://127.0.0.1:70000",
    "tcp://127.0.0.1:abc",
    "tcp://[::1",
    "tcp://a b:1",
    "http://127.0.0.1:8786",
    "127.0.0.1",
    "inproc://",
    "x" * 500,
]
GOOD = [
    "threads",
    "processes",
    "sync",
    "tcp://127.0.0.1:8786",
    "127.0.0.1:8786",
    "tls://scheduler.example.org:8786",
    "tcp://[::1]:8786",
    "ucx://node-3:8786",
    "inproc://10.0.0.1/4242/1",
]


def _digest(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _one_line(output: str, *needles: str) -> str:
    assert "Traceback" not in output, output
    lines = [ln for ln in output.splitlines() if ln.strip()]
    assert len(lines) == 1, output
    flat = " ".join(lines[0].split())
    assert flat.startswith("error:"), output
    for n in needles:
        assert n in flat, (n, output)
    return flat


@pytest.fixture(scope="module")
def take(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_take(tmp_path_factory.mktemp("sched") / "take.h5", n_events=5_000).path


@pytest.mark.slow
@pytest.mark.parametrize("value", BAD)
def test_bad_scheduler_is_refused_at_parse_time(take: Path, tmp_path: Path, value: str) -> None:
    before = _digest(take)
    out = tmp_path / "rec"
    r = runner.invoke(app, ["reconstruct", str(take), "--out", str(out), "--scheduler", value])
    assert r.exit_code == 2, r.output
    assert r.exception is None or isinstance(r.exception, SystemExit), r.exception
    _one_line(r.output, "--scheduler", "threads, processes, sync", "tcp://HOST:PORT")
    assert not out.exists()
    assert _digest(take) == before


@pytest.mark.parametrize("value", GOOD)
def test_accepted_forms(tmp_path: Path, value: str) -> None:
    assert ReconstructOptions(takes=[], out=tmp_path, scheduler=value).scheduler == value


@pytest.mark.slow
@settings(max_examples=200, deadline=None)
@given(st.text(max_size=40))
def test_any_scheduler_text_is_accepted_or_named(value: str) -> None:
    try:
        ReconstructOptions(takes=[], out=Path("x"), scheduler=value)
    except ValidationError as exc:
        err = exc.errors()[0]
        assert err["loc"] == ("scheduler",)
        assert "threads, processes, sync" in err["msg"]


@pytest.mark.slow
def test_unreachable_scheduler_fails_after_the_connect_timeout(
    take: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Port 1 on the loopback: nothing listens. The client gives up after CONNECT_TIMEOUT_S
    (made 1 s here) and says so in one line; no output directory is created."""
    pytest.importorskip("distributed")
    monkeypatch.setattr(reconstruct_scheduler, "CONNECT_TIMEOUT_S", 1)
    out = tmp_path / "rec"
    r = runner.invoke(app, ["reconstruct", str(take), "--out", str(out), "--scheduler", "tcp://127.0.0.1:1"])
    assert r.exit_code == 2, r.output
    _one_line(r.output, "--scheduler tcp://127.0.0.1:1", "no dask.distributed scheduler answered within 1 s")
    assert not out.exists()
