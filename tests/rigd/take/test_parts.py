"""Multi-host takes: part files joined into one take by external links (rigd.take.parts).

Synthetic parts: one `make_take` take split in two, the camera in host A's part (with the
trigger: the coordinator) and the event sensor in host B's; both hold the same pulses, as the
parts of one multi-host take do. The joined take must read, validate and summarize as the take
they came from, a missing or unsealed part must cost only its host's devices, and every hostile
variation of the links must be refused by name without reading what they point at.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from firmware_sim.testing.takes import make_take
from rigd.app.cli import app
from rigd.core.errors import TakeError, TakeFormatError
from rigd.take import Take
from rigd.take.calibration import store_calibration
from rigd.take.parts import PartRef, join_take, part_name
from rigd.take.validate import validate_take

STEM = "rig-take"
SECRET = b"not a take: private bytes\n" * 100


@pytest.fixture(scope="module")
def whole(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_take(tmp_path_factory.mktemp("parts") / "whole.h5").path


def _part(whole: Path, out: Path, drop: str) -> None:
    shutil.copy(whole, out)
    with h5py.File(out, "r+") as f:
        del f[drop]
        name = drop.rsplit("/", 1)[1]
        if f"sync/devices/{name}" in f:
            del f[f"sync/devices/{name}"]


def make_parts(whole: Path, d: Path) -> list[PartRef]:
    """Host A: cam0 and the trigger (coordinator); host B: ev0."""
    d.mkdir(exist_ok=True)
    a, b = d / part_name(STEM, "A"), d / part_name(STEM, "B")
    _part(whole, a, "events/ev0")
    _part(whole, b, "frames/cam0")
    return [PartRef("A", Path(a.name), ("cam0",)), PartRef("B", Path(b.name), ("ev0",))]


@pytest.fixture
def joined(whole: Path, tmp_path: Path) -> Path:
    refs = make_parts(whole, tmp_path / "takes")
    out = tmp_path / "takes" / f"{STEM}.h5"
    join_take(out, refs[0].file or Path(), refs)
    return out


def test_joined_take_reads_as_the_take_its_parts_came_from(whole: Path, joined: Path) -> None:
    with Take(whole) as w, Take(joined) as j:
        assert j.status == "complete"
        assert j.time_domain == "rig"
        assert j.take_id == STEM
        assert j.cameras == w.cameras
        assert j.event_sensors == w.event_sensors
        assert np.array_equal(j.pulses().t_us, w.pulses().t_us)
        assert np.array_equal(j.camera("cam0").timestamps_us, w.camera("cam0").timestamps_us)
        assert all(np.array_equal(j.camera("cam0").raw(i), w.camera("cam0").raw(i)) for i in range(9))
        ej, ew = j.sensor("ev0").events(), w.sensor("ev0").events()
        assert all(np.array_equal(getattr(ej, k), getattr(ew, k)) for k in "xypt")
        assert j.sync_report is not None
        assert w.sync_report is not None
        assert j.sync_report.devices == w.sync_report.devices
        s = j.summary()
        assert s.verdict == w.summary().verdict
        parts = j.parts
        assert parts is not None
        assert [(p.host, p.status, p.coordinator) for p in parts] == [
            ("A", "complete", True),
            ("B", "complete", False),
        ]
        assert all(p.sha256 and p.size == (joined.parent / (p.file or "")).stat().st_size for p in parts)
    with h5py.File(joined, "r") as f:
        link = f["events"].get("ev0", getlink=True)
        assert isinstance(link, h5py.ExternalLink)
        assert (link.filename, link.path) == (part_name(STEM, "B"), "/events/ev0")
    assert validate_take(joined) == []
    r = CliRunner().invoke(app, ["inspect", str(joined)])
    assert r.exit_code == 0, r.output
    assert f"part B (ev0): {part_name(STEM, 'B')} complete" in r.stdout


def test_a_missing_part_costs_its_hosts_devices_only(whole: Path, tmp_path: Path) -> None:
    refs = make_parts(whole, tmp_path / "takes")
    (tmp_path / "takes" / part_name(STEM, "B")).unlink()
    out = tmp_path / "takes" / f"{STEM}.h5"
    res = join_take(out, Path(part_name(STEM, "A")), refs, missing={"B": "host B stopped answering"})
    assert res.verdict.verdict == "degraded"
    assert res.missing_devices == ["ev0"]
    assert any(r.startswith("ev0: events lost") for r in res.verdict.reasons), res.verdict.reasons
    with Take(out) as t:
        assert t.event_sensors == []
        assert t.cameras == ["cam0"]
        assert len(t.camera("cam0")) == 9
        parts = t.parts
        assert parts is not None
        assert parts[1].status == "missing"
        assert "host B stopped answering" in (parts[1].reason or "")
        assert "rigd recover" in (parts[1].reason or "")
    assert validate_take(out) == []
    # the part arrives (gathered after `rigd recover` on B): joining again completes the take
    make_parts(whole, tmp_path / "takes")
    res = join_take(out, Path(part_name(STEM, "A")), refs)
    assert res.missing_devices == []
    assert res.verdict.verdict == "complete"


def test_an_unsealed_part_is_not_linked_and_says_to_recover_it(whole: Path, tmp_path: Path) -> None:
    refs = make_parts(whole, tmp_path / "takes")
    b = tmp_path / "takes" / part_name(STEM, "B")
    make_take(tmp_path / "raw.h5", finalize=False)
    _part(tmp_path / "raw.h5", b, "frames/cam0")
    res = join_take(tmp_path / "takes" / f"{STEM}.h5", Path(part_name(STEM, "A")), refs)
    entry = res.parts[1]
    assert entry.status == "unfinished"
    assert "rigd recover" in (entry.reason or "")
    assert res.verdict.verdict == "degraded"
    assert res.missing_devices == ["ev0"]


def test_a_part_holding_the_first_pulses_only_is_linked(whole: Path, tmp_path: Path) -> None:
    """A follower that died holds the pulses up to its last flush, a prefix of the
    coordinator's; once `rigd recover` sealed it on its host, it is this take's part."""
    refs = make_parts(whole, tmp_path / "takes")
    with h5py.File(tmp_path / "takes" / part_name(STEM, "B"), "r+") as f:
        for k in ("index", "t_us", "host_time_ns"):
            f[f"trigger/pulses/{k}"].resize((7,))
    out = tmp_path / "takes" / f"{STEM}.h5"
    res = join_take(out, Path(part_name(STEM, "A")), refs)
    assert res.parts[1].status == "complete"
    assert res.missing_devices == []
    with Take(out) as t:
        assert t.sensor("ev0").count == 20_000
        assert len(t.pulses().t_us) == 10
    assert validate_take(out) == []


def test_a_calibration_stored_into_the_joined_take_survives_joining_again(joined: Path) -> None:
    intrinsics = {
        "K": [[100.0, 0, 8], [0, 100.0, 6], [0, 0, 1]],
        "dist": [0.1, 0, 0, 0, 0],
        "image_size": [16, 12],
    }
    store_calibration(joined, "cam0", intrinsics, source="rigd calibrate intrinsics")
    refs = [
        PartRef("A", Path(part_name(STEM, "A")), ("cam0",)),
        PartRef("B", Path(part_name(STEM, "B")), ("ev0",)),
    ]
    join_take(joined, Path(part_name(STEM, "A")), refs)
    with Take(joined) as t:
        cal = t.calibration
        assert cal is not None
        assert np.allclose(cal["cam0"]["K"], intrinsics["K"])


def test_a_part_of_another_take_is_not_linked(whole: Path, tmp_path: Path) -> None:
    refs = make_parts(whole, tmp_path / "takes")
    with h5py.File(tmp_path / "takes" / part_name(STEM, "B"), "r+") as f:
        f["trigger/pulses/t_us"][3] += 1000
    res = join_take(tmp_path / "takes" / f"{STEM}.h5", Path(part_name(STEM, "A")), refs)
    assert res.parts[1].status == "foreign"
    assert res.missing_devices == ["ev0"]


def test_parts_that_cannot_form_one_take_are_refused(whole: Path, tmp_path: Path) -> None:
    refs = make_parts(whole, tmp_path / "takes")
    out = tmp_path / "takes" / f"{STEM}.h5"
    a = Path(part_name(STEM, "A"))
    with pytest.raises(TakeError, match="ev0 is planned on hosts A and B"):
        join_take(out, a, [PartRef("A", a, ("cam0", "ev0")), refs[1]])
    with pytest.raises(TakeError, match="holds cam0, which the plan does not give that host"):
        join_take(out, a, [PartRef("A", a, ()), PartRef("B", refs[1].file, ("ev0", "cam0x"))])
    with pytest.raises(TakeError, match=r"coordinator's part .* is not one of the parts"):
        join_take(out, Path("elsewhere.A.part.h5"), refs)
    shutil.copy(whole, out)
    with pytest.raises(TakeError, match="not a joined take; not overwritten"):
        join_take(out, a, refs)
    assert not list(out.parent.glob(".*joining"))


# -- hostile joins -----------------------------------------------------------------------------


def _relink(p: Path, hpath: str, filename: str, target: str | None = None) -> None:
    with h5py.File(p, "r+") as f:
        del f[hpath]
        f[hpath] = h5py.ExternalLink(filename, target or hpath)


def _manifest(p: Path, edit: dict[str, object]) -> None:
    with h5py.File(p, "r+") as f:
        entries = json.loads(f.attrs["parts_json"])
        entries[1].update(edit)
        f.attrs["parts_json"] = json.dumps(entries)


def _refused(p: Path, match: str) -> None:
    with pytest.raises(TakeFormatError, match=match), Take(p) as t:
        t.sensor("ev0").events()
    problems = validate_take(p)
    assert any(re.search(match, m) for m in problems), problems
    r = CliRunner().invoke(app, ["inspect", str(p)])
    assert r.exit_code == 2, r.output
    assert "Traceback" not in r.output
    assert "private bytes" not in r.output


def test_link_to_a_file_outside_the_manifest_is_refused(joined: Path, tmp_path: Path) -> None:
    _relink(joined, "/events/ev0", "/etc/passwd")
    _refused(joined, "/events/ev0: external link to '/etc/passwd', which the take's parts manifest")


def test_manifest_naming_a_path_outside_the_directory_is_refused(joined: Path) -> None:
    _manifest(joined, {"file": "../x.part.h5"})
    _refused(joined, "parts_json: 1.file")


def test_a_part_name_that_is_a_symlink_out_of_the_directory_is_refused(joined: Path, tmp_path: Path) -> None:
    secret = tmp_path / "secret.part.h5"
    secret.write_bytes(SECRET)
    b = joined.parent / part_name(STEM, "B")
    b.unlink()
    b.symlink_to(secret)
    _refused(joined, "/events/ev0: external link to .* leaves the take's directory")


def test_a_part_that_is_a_fifo_is_not_opened(joined: Path) -> None:
    b = joined.parent / part_name(STEM, "B")
    b.unlink()
    os.mkfifo(b)
    _refused(joined, "is not a regular file")


def test_a_part_linking_back_to_the_joined_take_is_refused(joined: Path) -> None:
    b = joined.parent / part_name(STEM, "B")
    with h5py.File(b, "r+") as f:
        f["events/ev1"] = h5py.ExternalLink(joined.name, "/events/ev0")
    _refused(joined, "events/ev1: is an external link .* a part of a multi-host take holds none")


def test_a_part_with_its_own_external_link_is_refused(joined: Path, tmp_path: Path) -> None:
    b = joined.parent / part_name(STEM, "B")
    other = joined.parent / "other.h5"
    with h5py.File(other, "w") as o:
        o["t"] = np.frombuffer(SECRET[:800], np.int64)
    with h5py.File(b, "r+") as f:
        del f["events/ev0/trigger/t"]
        f["events/ev0/trigger/t"] = h5py.ExternalLink(other.name, "/t")
    _refused(joined, "trigger/t: is an external link .* a part of a multi-host take holds none")


def test_a_link_elsewhere_in_its_part_or_the_take_is_refused(joined: Path) -> None:
    _relink(joined, "/events/ev0", part_name(STEM, "B"), "/trigger/pulses")
    _refused(joined, "external link to '/trigger/pulses' in its part")


def test_a_link_outside_the_device_groups_is_refused(joined: Path) -> None:
    _relink(joined, "/trigger/pulses", part_name(STEM, "B"))
    with pytest.raises(TakeFormatError, match="/trigger/pulses: is an external link"):
        Take(joined)


def test_a_take_moved_without_its_parts_says_so(joined: Path) -> None:
    (joined.parent / part_name(STEM, "B")).unlink()
    _refused(
        joined, rf"/events/ev0: its part {re.escape(part_name(STEM, 'B'))} is not in the take's directory"
    )


def test_a_link_to_the_take_itself_is_refused(joined: Path) -> None:
    loop = joined.parent / "loop.A.part.h5"
    shutil.copy(joined, loop)
    _manifest(loop, {"file": loop.name})
    _relink(loop, "/events/ev0", loop.name)
    with pytest.raises(TakeFormatError, match="leads back to the take itself"):
        Take(loop)


def test_hdf5s_own_search_path_is_never_used(
    joined: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A file of the part's name in HDF5_EXT_PREFIX or the working directory is never read."""
    evil = tmp_path / "evil"
    evil.mkdir()
    decoy = evil / part_name(STEM, "B")
    make_take(decoy, n_events=500)
    monkeypatch.setenv("HDF5_EXT_PREFIX", str(evil))
    monkeypatch.chdir(evil)
    with Take(joined) as t:
        assert t.sensor("ev0").count == 20_000


def test_validation_names_a_manifest_that_does_not_match_the_links(joined: Path) -> None:
    with h5py.File(joined, "r+") as f:
        entries = json.loads(f.attrs["parts_json"])
        entries[0]["devices"] = ["cam0", "ev0"]
        f.attrs["parts_json"] = json.dumps(entries)
    problems = validate_take(joined)
    assert any("device ev0 is in the parts of A and B" in p for p in problems), problems
    assert any("/events/ev0: is not linked to its part" in p for p in problems), problems


def test_takes_lists_a_joined_take_once_with_its_parts_and_a_lone_part_as_its_hosts(joined: Path) -> None:
    d = joined.parent
    r = CliRunner().invoke(app, ["takes", str(d), "--json"])
    assert r.exit_code == 0, r.output
    rows = json.loads(r.stdout)
    assert [row["name"] for row in rows] == [STEM]
    assert sorted(rows[0]["parts"]) == [part_name(STEM, "A"), part_name(STEM, "B")]
    parts = [d / part_name(STEM, h) for h in "AB"]
    assert rows[0]["parts_bytes"] == sum(p.stat().st_size for p in parts)
    table = CliRunner().invoke(app, ["takes", str(d)], env={"COLUMNS": "200"})
    assert "2 host parts" in table.stdout
    # on a follower host only its part is there: listed as that host's part of the take
    joined.unlink()
    parts[0].unlink()
    r = CliRunner().invoke(app, ["takes", str(d), "--json"])
    (row,) = json.loads(r.stdout)
    assert (row["name"], row["part_of"], row["part_host"], row["verdict"]) == (
        f"{STEM}.B.part",
        STEM,
        "B",
        "complete",
    )
    table = CliRunner().invoke(app, ["takes", str(d)], env={"COLUMNS": "200"})
    assert f"host B's part of {STEM}" in table.stdout
