"""The default sim rig's devices captured as three parts (cameras and the box, ev0 and the box,
ev1 and the box, each in a fresh process: its own world) joined into one take equal the whole
rig's take of the same config: on the virtual clock the data is a function of config and seed."""

from __future__ import annotations

import multiprocessing as mp
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from rigd.app.cli import app
from rigd.take import Take
from rigd.take.parts import PartRef, join_take, part_name
from rigd.take.validate import validate_take

pytestmark = pytest.mark.slow  # four captures in fresh processes, exports and reconstructions: ~20 s

HOSTS = {"A": ("cam0", "cam1", "cam2"), "B": ("ev0",), "C": ("ev1",)}


def capture(path: str, devices: tuple[str, ...]) -> None:
    """Capture the small sim rig's `devices` (and its trigger) for 1 s of pulses into `path`."""
    from rigd.app.capture.run import run_capture
    from rigd.app.config import RigConfig, default_sim_rig

    cfg = default_sim_rig(world="parts", resolution=(160, 120), clock="virtual", pixel_format="mono8")
    data = cfg.model_dump(mode="json")
    data["cameras"] = [c for c in data["cameras"] if c["name"] in devices]
    data["event_sensors"] = [s for s in data["event_sensors"] if s["name"] in devices]
    data["writer"].update(disk_reserve_mb=0, disk_ballast_mb=24)
    out = Path(path)
    run_capture(RigConfig.from_data(data), out.parent, 1.0, path=out)


def _in_process(path: Path, devices: tuple[str, ...]) -> None:
    proc = mp.get_context("spawn").Process(target=capture, args=(str(path), devices))
    proc.start()
    proc.join(300)
    assert proc.exitcode == 0, f"capture of {devices} into {path} exited {proc.exitcode}"


def test_joined_parts_equal_the_single_rig_take(tmp_path: Path) -> None:
    single = tmp_path / "single" / "single.h5"
    single.parent.mkdir()
    _in_process(single, tuple(d for devs in HOSTS.values() for d in devs))
    takes = tmp_path / "split"
    takes.mkdir()
    refs = []
    for host, devices in HOSTS.items():
        p = takes / part_name("split", host)
        _in_process(p, devices)
        refs.append(PartRef(host, Path(p.name), devices))
    res = join_take(takes / "split.h5", Path(part_name("split", "A")), refs)
    assert res.verdict.verdict == "complete", res.verdict.line()
    assert validate_take(takes / "split.h5") == []
    with Take(single) as s, Take(takes / "split.h5") as j:
        assert j.cameras == s.cameras
        assert j.event_sensors == s.event_sensors
        ps, pj = s.pulses(), j.pulses()
        assert np.array_equal(ps.index, pj.index)
        assert np.array_equal(ps.t_us, pj.t_us)
        assert ps.index.size >= 29
        rs, rj = s.sync_report, j.sync_report
        assert rs is not None
        assert rj is not None
        assert rj.devices == rs.devices
        assert (rj.n_pulses, rj.pulses_seen_by_no_device, rj.losses) == (
            rs.n_pulses,
            rs.pulses_seen_by_no_device,
            rs.losses,
        )
        for cam in s.cameras:
            a, b = s.camera(cam, demosaic=False), j.camera(cam, demosaic=False)
            assert len(a) == len(b) > 0
            assert np.array_equal(a.timestamps_us, b.timestamps_us)
            assert all(np.array_equal(a.raw(i), b.raw(i)) for i in range(len(a)))
        for sensor in s.event_sensors:
            ea, eb = s.sensor(sensor).events(), j.sensor(sensor).events()
            assert len(ea) == len(eb) > 0
            assert all(np.array_equal(getattr(ea, k), getattr(eb, k)) for k in "xypt")
            assert np.array_equal(s.sensor(sensor).triggers.t, j.sensor(sensor).triggers.t)
        cj, cs = j.calibration, s.calibration  # ground truth in the whole rig's frame
        assert cj is not None
        assert cs is not None
        assert cj.keys() == cs.keys()
        for dev, cal in cs.items():
            for key in ("K", "dist", "R", "t"):
                assert np.allclose(cj[dev][key], cal[key], atol=1e-9), (dev, key)
    _same_products(single, takes / "split.h5", tmp_path)


def _same_products(single: Path, joined: Path, tmp_path: Path) -> None:
    """`rigd export` and `rigd reconstruct` give the same files from both takes."""
    runner = CliRunner()
    for name, argv in (
        ("export", ["export", "--format", "nerfstudio"]),
        ("reconstruct", ["reconstruct", "--scheduler", "sync"]),
    ):
        outs = []
        for take in (single, joined):
            out = tmp_path / f"{name}-{take.stem}"
            r = runner.invoke(app, [*argv, str(take), "--out", str(out)])
            assert r.exit_code == 0, r.output
            outs.append(out)
        files = [
            {p.relative_to(o).as_posix().replace(t.stem, "TAKE"): p for p in o.rglob("*") if p.is_file()}
            for o, t in zip(outs, (single, joined), strict=True)
        ]
        assert files[0].keys() == files[1].keys()
        # the reports name their take (path, id): compared with the names swapped
        differ = [
            k
            for k in files[0]
            if files[0][k].read_bytes().replace(single.stem.encode(), joined.stem.encode())
            != files[1][k].read_bytes()
            and k != "export.json"  # also says how long the export took
        ]
        assert differ == [], f"{name}: {differ}"
