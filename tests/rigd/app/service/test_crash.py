"""SIGKILL the daemon at random moments of a take, 20 times: every take opens with plain
h5py, holds everything the sim delivered more than a flush interval (plus SLACK_S for the
queue and the flush itself) before the kill (checked against the simulator's own journal),
and is sealed when the daemon restarts."""

from __future__ import annotations

import json
import os
import random
import signal
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

from rigd.app.service.client import DaemonClient
from rigd.app.testing.daemon import endpoints, small_rig, spawn_daemon
from rigd.take.reader import Take
from rigd.take.validate import validate_take

pytestmark = pytest.mark.slow

N_KILLS = 20
FLUSH_S = 0.5
#: On top of the flush interval: the capture queue, the writer's wake-up, and the flush itself
#: (writing the buffers, then fsync). A loaded CI machine needs the room.
SLACK_S = 0.5


def _journal(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _plain_event_times(g: h5py.Group) -> np.ndarray:
    """Event times of an unrecovered take with plain h5py (docs/take-format.md): the whole
    chunks in `t`, continued by the tail slot that starts where they end. A sensor stored as
    EVT words has no times to read plainly: the reader decodes its flushed words (tail too)."""
    if g.attrs.get("storage") == "evt_words":
        with Take(g.file.filename) as take:
            return take.sensor(g.name.rsplit("/", 1)[-1]).events().t
    t = g["t"][...]
    for slot, (start, rows) in enumerate(g.attrs.get("tail_meta", np.zeros((2, 2), np.int64))):
        if start == t.shape[0] and rows:
            t = np.concatenate([t, g["tail_t"][slot, :rows]])
    return t


def _check_take(take: Path, truth: list[dict[str, Any]], cutoff_ns: int, kill_ns: int) -> dict[str, float]:
    """Everything delivered before `cutoff_ns` is in the take (device times, unfinalized)."""
    old = [r for r in truth if r["host_time_ns"] < cutoff_ns]
    delivered = {(r["dev"], int(r["t_device_us"])): r["host_time_ns"] for r in old if r["kind"] == "frame"}
    frames: dict[str, set[int]] = defaultdict(set)
    ev_n: dict[str, int] = defaultdict(int)
    ev_last: dict[str, int] = {}
    pulses: set[int] = set()
    for r in old:
        if r["kind"] == "frame":
            frames[r["dev"]].add(int(r["t_device_us"]))
        elif r["kind"] == "events":
            ev_n[r["dev"]] += int(r["n"])
            ev_last[r["dev"]] = max(ev_last.get(r["dev"], -(2**62)), int(r["t_last_device_us"]))
        elif r["kind"] == "pulse":
            pulses.add(int(r["index"]))
    with h5py.File(take, "r") as f:  # plain h5py, no recovery tools
        assert f.attrs["status"] == "recording"
        for cam, times in frames.items():
            have = set(f[f"frames/{cam}/t_exposure_start_device_us"][...].tolist())
            missing = times - have
            ages = sorted((kill_ns - delivered[cam, t]) / 1e9 for t in missing)
            assert not missing, (
                f"{take.name} {cam}: {len(missing)} frames delivered before the cutoff missing, "
                f"delivered {ages[0]:.3f}-{ages[-1]:.3f} s before the kill; the take has "
                f"{len(have)} frames, last flush {f.attrs.get('last_flush_utc')!r}"
            )
        for sen, n in ev_n.items():
            t = _plain_event_times(f[f"events/{sen}"])
            assert t.shape[0] >= n, f"{take.name} {sen}: {t.shape[0]} events < {n} delivered"
            assert int(t[n - 1]) <= ev_last[sen]
            assert int(t[t.shape[0] - 1]) >= ev_last[sen]
        have_p = set(f["trigger/pulses/index"][...].tolist())
        assert pulses <= have_p, f"{take.name}: pulse records {sorted(pulses - have_p)[:5]} missing"
        n_frames = {c: f[f"frames/{c}/t_exposure_start_device_us"].shape[0] for c in f["frames"]}
    return {
        "frames": float(sum(n_frames.values())),
        "old_frames": float(sum(len(v) for v in frames.values())),
    }


def test_sigkill_twenty_times_takes_survive_and_are_sealed(runtime_dir: Path, tmp_path: Path) -> None:
    take_dir = tmp_path / "takes"
    cfg = small_rig("crash", take_dir=str(take_dir), thumbnail_interval_s=0)
    data = cfg.model_dump(mode="json")
    data["writer"]["flush_interval_s"] = FLUSH_S
    cfg = type(cfg).from_data(data)
    rng = random.Random(7)
    takes: list[tuple[Path, int]] = []
    log = tmp_path / "daemon.log"
    lag: list[float] = []
    empty = 0
    for i in range(N_KILLS + 1):
        truth_path = tmp_path / f"truth-{i}.jsonl"
        proc = spawn_daemon(cfg, runtime_dir, log, env={"RIGD_SIM_TRUTH_LOG": str(truth_path)})
        client = DaemonClient(endpoints(runtime_dir)["control"], timeout_s=20)
        try:
            if takes:  # the restart sealed the previous take
                prev, _ = takes[-1]
                with h5py.File(prev, "r") as f:
                    attrs = dict(f.attrs)
                assert "recovered_utc" in attrs, attrs
                if int(attrs.get("flush_count", 0)) == 0:
                    # Killed before its first flush: nothing recorded, sealed as failed with why.
                    assert attrs["status"] == "failed", attrs
                    empty += 1
                else:
                    assert attrs["status"] == "complete", (prev, attrs)
                    problems = validate_take(prev)
                    assert not problems, problems
            if i == N_KILLS:
                break
            path = Path(client.call("capture")["take"])
            time.sleep(rng.uniform(0.5, 3.0))
            kill_ns = time.monotonic_ns()
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
        finally:
            client.close()
            if proc.poll() is None and (i == N_KILLS or sys.exc_info()[0] is not None):
                proc.terminate()  # the last round, or a failure: no daemon left behind
                proc.wait(timeout=60)
        cutoff = kill_ns - int((FLUSH_S + SLACK_S) * 1e9)
        stats = _check_take(path, _journal(truth_path), cutoff, kill_ns)
        lag.append(stats["frames"] - stats["old_frames"])
        takes.append((path, kill_ns))
    assert len(takes) == N_KILLS
    print(f"frames past the cutoff per kill: {np.round(lag, 0).tolist()}; killed before a flush: {empty}")
    assert empty <= 5
