"""A take in take_dir that points HDF5 at a FIFO (issue: its read blocked every thread of the
daemon): start-up recovery, the console's take list and previews meet it without waiting on
it, a take runs to completion meanwhile, and a restarted daemon is ready with it present."""

from __future__ import annotations

import json
import os
import shutil
import threading
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest

from firmware_sim.testing.takes import make_take
from rigd.app.console.takes import TakeList
from rigd.app.service.client import DaemonClient
from rigd.app.testing.console import ConsoleDaemon
from rigd.app.testing.crash import unfinished
from rigd.app.testing.daemon import wait_idle
from rigd.core.errors import TakeError
from rigd.take.isolated import TakeReadTimeoutError, run_isolated


def _point_at(p: Path, fifo: Path, hpath: str) -> None:
    with h5py.File(p, "r+") as f:
        shape, dtype = f[hpath].shape, f[hpath].dtype
        del f[hpath]
        n = int(np.prod(shape)) * dtype.itemsize
        f.create_dataset(hpath, shape, dtype, external=[(str(fifo), 0, n)])


def _fifo_sealed(take_dir: Path, scratch: Path) -> Path:
    fifo = scratch / "pipe"
    if not fifo.exists():
        os.mkfifo(fifo)
    sealed = take_dir / "fifo-sealed.h5"
    shutil.copy(make_take(scratch / "done.h5").path, sealed)
    _point_at(sealed, fifo, "frames/cam0/images")
    return sealed


def _fifo_unfinished(take_dir: Path, scratch: Path) -> Path:
    take_dir.mkdir(parents=True, exist_ok=True)
    fifo = scratch / "pipe"
    if not fifo.exists():
        os.mkfifo(fifo)
    p = unfinished(take_dir / "fifo-unfinished.h5", n=4)
    _point_at(p, fifo, "events/ev0/t")
    return p


@pytest.mark.slow
def test_fifo_takes_cost_the_daemon_nothing(
    console_daemon: Callable[..., ConsoleDaemon], tmp_path: Path
) -> None:
    take_dir = tmp_path / "takes"
    unfinished_fifo = _fifo_unfinished(take_dir, tmp_path)
    cd = console_daemon()  # start-up recovery met the unfinished one: it returns, and serves
    problems = {r["path"]: r for r in cd.daemon.recovered}
    assert "external file" in problems[str(unfinished_fifo)]["error"]
    sealed_fifo = _fifo_sealed(take_dir, tmp_path)  # arrives while the daemon serves
    client = DaemonClient(cd.config.service.control_endpoint, timeout_s=10)
    with cd.http() as http:
        assert http.get("/api/takes").status_code == 200
        client.call("capture", duration_s=1.0, label="beside-fifo")
        seen: list[int] = []
        lister = threading.Thread(target=lambda: seen.append(http.get("/api/takes").status_code))
        lister.start()
        while lister.is_alive():  # the daemon answers while the list is read
            assert client.call("status")["state"] in ("capturing", "finalizing", "idle")
            lister.join(0.05)
        assert seen == [200]
        last = wait_idle(client)
        entries = {e["name"]: e for e in http.get("/api/takes").json()["takes"]}
        r = http.get("/api/takes/fifo-sealed.h5/preview/cam0.jpg")
        assert r.status_code >= 400
        assert "external file" in r.text
    client.close()
    assert last["last_take"]["status"] == "complete"
    assert entries["fifo-sealed.h5"]["verdict"] == "damaged"
    assert "external file" in entries["fifo-sealed.h5"]["error"]
    cd.daemon.shutdown()
    cd.thread.join(timeout=60)
    again = console_daemon()  # restarts ready with the FIFO take in take_dir (moved aside, kept)
    with DaemonClient(again.config.service.control_endpoint, timeout_s=10) as c2:
        assert c2.call("ping")["state"] == "idle"
    moved = {r["path"]: r["moved_to"] for r in again.daemon.recovered}
    assert Path(moved[str(sealed_fifo)]).is_file()


def _read_fifo(path: Path) -> bytes:
    return path.read_bytes()


def test_a_read_that_blocks_costs_its_deadline_only(tmp_path: Path) -> None:
    """The bound under the structural check: a read that blocks (here on a FIFO no one writes)
    is killed at its deadline and reported, never waited on."""
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    with pytest.raises(TakeReadTimeoutError, match=r"did not finish within 0\.5 s"):
        run_isolated(_read_fifo, fifo, timeout_s=0.5, what=str(fifo))


def test_take_list_and_preview_refuse_fifo_takes(tmp_path: Path) -> None:
    take_dir = tmp_path / "takes"
    _fifo_unfinished(take_dir, tmp_path)
    _fifo_sealed(take_dir, tmp_path)
    entries = {e.name: e for e in TakeList(take_dir, read_timeout_s=20).entries()}
    assert entries["fifo-sealed.h5"].verdict == "damaged"
    assert entries["fifo-unfinished.h5"].verdict == "damaged"
    with pytest.raises(TakeError, match="external file"):
        TakeList(take_dir).preview("fifo-sealed.h5", "cam0")


def test_rigd_takes_and_recover_answer_with_fifo_takes(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from rigd.app.cli import app

    take_dir = tmp_path / "takes"
    unfinished_fifo = _fifo_unfinished(take_dir, tmp_path)
    _fifo_sealed(take_dir, tmp_path)
    runner = CliRunner()
    listed = runner.invoke(app, ["takes", str(take_dir), "--json"])
    assert listed.exit_code == 0, listed.output
    assert [r["verdict"] for r in json.loads(listed.stdout)] == ["damaged", "damaged"]
    rec = runner.invoke(app, ["recover", str(take_dir)])
    assert "Traceback" not in rec.output
    assert str(unfinished_fifo) in rec.output
    assert "external file" in rec.output
