"""`rigd capture` against hostile inputs: every numeric sim and replay spec parameter, every
numeric rig config key, the duration and the take directory. Each is refused up front with one
line naming what is wrong and where (exit 2, no traceback) and nothing is written; a capture
with a pathological input ends on one SIGTERM; a clean stop records no losses and does not wait
out `writer.stop_backlog_s`."""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any, get_args, get_origin

import h5py
import pytest
from pydantic import BaseModel
from typer.testing import CliRunner

from drivers import registry
from drivers.registry import DeviceSpec, open_device
from firmware_sim.rgb_camera import open_sim_camera
from firmware_sim.spec_params import (
    ReplayCameraParams,
    ReplaySensorParams,
    ReplayTriggerParams,
    SimCameraParams,
    SimEventSensorParams,
    SimTriggerParams,
    SpecParams,
    allowed_range,
)
from firmware_sim.testing.takes import make_take
from firmware_sim.world import reset_world
from rigd.app.capture.session import CaptureSession
from rigd.app.cli import app
from rigd.app.config import RigConfig, default_sim_rig
from rigd.core.errors import ConfigError
from rigd.products.convert import convert
from rigd.take import Take


def _small_rig(world: str, **writer: Any) -> RigConfig:
    cfg = default_sim_rig(world=world, resolution=(160, 120), clock="virtual")
    data = cfg.model_dump(mode="json")
    data["writer"].update({"disk_reserve_mb": 0, "disk_ballast_mb": 24, **writer})
    return RigConfig.from_data(data)


# -- sim and replay spec parameters ------------------------------------------------------------
KINDS: dict[str, tuple[str, type[SpecParams], str, str]] = {
    # name: (device kind, model, spec prefix, device named in the error)
    "sim camera": ("rgb_camera", SimCameraParams, "sim://hostile/cam0?", "camera cam0"),
    "sim event sensor": ("event_sensor", SimEventSensorParams, "sim://hostile/ev0?", "event sensor ev0"),
    "sim trigger": ("trigger", SimTriggerParams, "sim://hostile/trigger?", "trigger box"),
    "replay camera": (
        "rgb_camera",
        ReplayCameraParams,
        "replay:///nowhere/take.h5?device=cam0&",
        "replayed camera cam0",
    ),
    "replay event sensor": (
        "event_sensor",
        ReplaySensorParams,
        "replay:///nowhere/take.h5?device=ev0&",
        "replayed event sensor ev0",
    ),
    "replay trigger": (
        "trigger",
        ReplayTriggerParams,
        "replay:///nowhere/take.h5?device=trigger&",
        "replayed trigger box",
    ),
}


def _numeric(model: type[BaseModel], name: str) -> type | None:
    """int or float for a numeric field (`X | None` included), else None."""
    annotation = model.model_fields[name].annotation
    for arg in (annotation, *get_args(annotation)):
        if arg in (int, float):
            return arg  # type: ignore[no-any-return]
        inner = get_args(arg)
        if inner and inner[0] in (int, float):
            return inner[0]  # type: ignore[no-any-return]
    return None


def _spec_variants() -> Iterator[tuple[str, str, str]]:
    """(kind, parameter, query value) for every numeric parameter of every device kind."""
    for kind, (_, model, _, _) in KINDS.items():
        for name in model.model_fields:
            typ = _numeric(model, name)
            if typ is None:
                continue
            values = ["nan", "inf", "-inf", "1e300" if typ is float else str(10**30)]
            rng = allowed_range(model, name) or ""
            if rng.startswith(("0..", "1..", ">")):
                values.append("-1")
            values.append("repeated")
            for value in values:
                yield kind, name, value


@pytest.mark.slow
@pytest.mark.parametrize(("kind", "param", "value"), list(_spec_variants()))
def test_spec_parameter_is_refused_naming_device_parameter_and_range(
    kind: str, param: str, value: str
) -> None:
    dev_kind, model, prefix, device = KINDS[kind]
    query = f"{param}=1&{param}=1" if value == "repeated" else f"{param}={value}"
    with pytest.raises(ConfigError) as err:
        open_device(dev_kind, prefix + query)  # type: ignore[call-overload]
    msg = str(err.value)
    assert "\n" not in msg
    assert f"({device})" in msg, msg
    assert param in msg, msg
    if value == "repeated":
        assert "more than once" in msg, msg
    else:
        assert f"allowed: {allowed_range(model, param)}" in msg, msg


@pytest.mark.parametrize("kind", ["sim camera", "sim trigger", "replay camera", "replay trigger"])
@pytest.mark.parametrize("value", ["1,x", "1,\u00b2", "-3", "99999999999", "1.5"])
def test_index_lists_are_refused_naming_the_bad_entry(kind: str, value: str) -> None:
    dev_kind, _model, prefix, device = KINDS[kind]
    param = "drop_pulses" if dev_kind == "trigger" else "drop_frames"
    with pytest.raises(ConfigError, match=f"\\({device}\\): {param}=.* is not an index") as err:
        open_device(dev_kind, f"{prefix}{param}={value}")  # type: ignore[call-overload]
    assert "\n" not in str(err.value)


def test_every_sim_spec_parameter_has_a_model_field() -> None:
    """The factories' own lists of parameters and the models agree: no parameter escapes."""
    from firmware_sim.placement import PLACEMENT_PARAMS
    from firmware_sim.trigger_box import BOX_PARAMS

    assert set(SimTriggerParams.model_fields) == BOX_PARAMS
    assert set(SimCameraParams.model_fields) >= PLACEMENT_PARAMS
    assert set(SimEventSensorParams.model_fields) >= PLACEMENT_PARAMS


@pytest.mark.parametrize(
    ("query", "words"),
    [
        ("seed=-1", ["camera cam0", "seed='-1'", "0..4294967295"]),
        ("offset_us=1e300", ["camera cam0", "offset_us='1e300'", "allowed"]),
        ("width=65535&height=65535", ["camera cam0", "width='65535'", "1..8192"]),
        ("drift_ppm=nan", ["camera cam0", "drift_ppm='nan'", "finite"]),
        ("width=100&width=200", ["camera cam0", "width", "more than once"]),
    ],
)
@pytest.mark.slow
def test_capture_refuses_a_hostile_sim_spec_and_writes_nothing(
    tmp_path: Path, query: str, words: list[str]
) -> None:
    world = f"hostile-{uuid.uuid4().hex[:8]}"
    cfg = _small_rig(world)
    cfg.cameras[0].spec = f"sim://{world}/cam0?{query}&clock=virtual"
    rig = tmp_path / "rig.json"
    rig.write_text(cfg.model_dump_json())
    out = tmp_path / "takes"
    result = CliRunner().invoke(app, ["capture", "--local", "-c", str(rig), "-d", "1", "-o", str(out)])
    _one_line_refusal(result, words)
    assert not out.exists()


# -- rig config numbers -------------------------------------------------------------------------
def _config_keys(model: type[BaseModel], data: Any, path: tuple[Any, ...] = ()) -> Iterator[tuple[Any, ...]]:
    """Key paths of every numeric field of the config (`writer.event_chunk`, ...), walking the
    default sim rig's data so list entries (cameras.0) are reached."""
    for name, field in model.model_fields.items():
        annotation = field.annotation
        sub = [
            a for a in (annotation, *get_args(annotation)) if isinstance(a, type) and issubclass(a, BaseModel)
        ]
        if _numeric(model, name) is not None:
            yield (*path, name)
        elif sub and isinstance(data.get(name), dict):
            yield from _config_keys(sub[0], data[name], (*path, name))
        elif get_origin(annotation) is list and isinstance(data.get(name), list) and data[name]:
            (item,) = get_args(annotation)
            yield from _config_keys(item, data[name][0], (*path, name, 0))


_RIG_DATA = json.loads(default_sim_rig().model_dump_json())
_RIG_DATA["service"]["curve"] = None
CONFIG_KEYS = list(_config_keys(RigConfig, _RIG_DATA))


def test_the_config_walk_reaches_the_settings() -> None:
    names = {".".join(map(str, k)) for k in CONFIG_KEYS}
    for key in (
        "trigger.settings.rate_hz",
        "cameras.0.settings.exposure_us",
        "event_sensors.0.settings.trigger_in_channel",
        "writer.event_chunk",
        "service.metrics_port",
    ):
        assert key in names, sorted(names)


@pytest.mark.parametrize("value", [True, "1", 1e30], ids=["true", "string", "1e30"])
@pytest.mark.parametrize("key", CONFIG_KEYS, ids=[".".join(map(str, k)) for k in CONFIG_KEYS])
def test_config_number_is_strict_and_bounded(tmp_path: Path, key: tuple[Any, ...], value: Any) -> None:
    data = json.loads(json.dumps(_RIG_DATA))
    node = data
    for part in key[:-1]:
        node = node[part]
    node[key[-1]] = value
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ConfigError) as err:
        RigConfig.load(path)
    msg = str(err.value)
    assert str(path) in msg, msg
    assert ".".join(map(str, key)) in msg, msg
    assert "\n" not in msg


# -- duration and take directory ------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("duration", ["nan", "inf", "-inf", "1e308", "0", "-1", "1e9", "604801"])
@pytest.mark.parametrize("local", [False, True], ids=["any", "local"])
def test_capture_refuses_a_bad_duration_and_creates_nothing(
    tmp_path: Path, duration: str, local: bool
) -> None:
    out = tmp_path / "takes"
    argv = ["capture", "--sim-clock", "virtual", "-d", duration, "-o", str(out)]
    result = CliRunner().invoke(app, argv + (["--local"] if local else []))
    _one_line_refusal(result, ["--duration", "7 days"])
    assert not out.exists()


def _out_is_a_file(d: Path) -> Path:
    (d / "f").write_text("keep me")
    return d / "f"


def _out_under_a_file(d: Path) -> Path:
    return _out_is_a_file(d) / "sub"


def _out_unwritable(d: Path) -> Path:
    locked = d / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    return locked / "takes"


@pytest.mark.parametrize("make", [_out_is_a_file, _out_under_a_file, _out_unwritable])
def test_capture_refuses_a_bad_out_before_opening_devices(tmp_path: Path, make: Any) -> None:
    if make is _out_unwritable and os.geteuid() == 0:
        pytest.skip("root writes to any directory")
    out = make(tmp_path)
    before = sorted(p.name for p in tmp_path.rglob("*"))
    result = CliRunner().invoke(
        app, ["capture", "--local", "--sim-clock", "virtual", "-d", "1", "-o", str(out)]
    )
    _one_line_refusal(result, ["--out", str(out)])
    assert sorted(p.name for p in tmp_path.rglob("*")) == before
    if (tmp_path / "f").exists():
        assert (tmp_path / "f").read_text() == "keep me"


# -- replay ---------------------------------------------------------------------------------------
@pytest.mark.slow
def test_replay_of_a_converted_take_says_what_it_lacks(tmp_path: Path) -> None:
    make_take(tmp_path / "src.h5")
    convert(tmp_path / "src.h5", tmp_path / "ev0.raw", sensor="ev0")
    convert(tmp_path / "ev0.raw", tmp_path / "conv.h5")
    out = tmp_path / "takes"
    result = CliRunner().invoke(
        app, ["capture", "--replay", str(tmp_path / "conv.h5"), "--sim-clock", "virtual", "-o", str(out)]
    )
    _one_line_refusal(result, ["no trigger box and no trigger pulses", "rigd convert", "ev0.raw"])
    assert "validation error" not in result.output
    assert not out.exists()


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A short finalized take of the sim rig on virtual time (the replays' source)."""
    session = CaptureSession(
        _small_rig(f"rec-{uuid.uuid4().hex[:8]}"), tmp_path_factory.mktemp("rec"), duration_s=0.3
    )
    session.start()
    result = session.wait(240)
    assert result is not None
    return result.path


def _extreme_clock_map(src: Path, dst: Path) -> Path:
    dst.write_bytes(src.read_bytes())
    with h5py.File(dst, "r+") as f:
        report = json.loads(f["sync/report_json"][()])
        report["devices"]["ev0"]["device_ref_us"] = 2**62
        del f["sync/report_json"]
        f["sync/report_json"] = json.dumps(report)
    return dst


# -- one signal ends a capture --------------------------------------------------------------------
def _jitter_rig(d: Path) -> list[str]:
    cfg = default_sim_rig(world=f"jit-{uuid.uuid4().hex[:8]}", resolution=(160, 120))
    data = cfg.model_dump(mode="json")
    data["trigger"]["spec"] = data["trigger"]["spec"].replace("jitter_us=2", "jitter_us=1e9")
    data["writer"].update({"disk_reserve_mb": 0, "disk_ballast_mb": 24, "stop_backlog_s": 1.0})
    (d / "rig.json").write_text(json.dumps(data))
    return ["--config", str(d / "rig.json"), "--duration", "60"]


@pytest.mark.slow
@pytest.mark.parametrize("case", ["jitter", "clock map"])
def test_one_sigterm_ends_a_pathological_capture_within_the_bound(
    tmp_path: Path, recorded: Path, case: str
) -> None:
    """The capture is refused up front (exit 2, one line) or, if it runs, the first SIGTERM
    ends it within the stop bound with a finalized take. Waits on its output, not on sleeps."""
    if case == "jitter":
        argv = _jitter_rig(tmp_path)
        expect = "jitter_us"
    else:
        argv = [
            "--replay",
            str(_extreme_clock_map(recorded, tmp_path / "extreme.h5")),
            "--sim-clock",
            "virtual",
        ]
        expect = "device_ref_us"
    out = tmp_path / "takes"
    cmd = [sys.executable, "-m", "rigd.app.cli", "capture", "--local", *argv, "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    lines: queue.Queue[str | None] = queue.Queue()

    def pump() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            lines.put(line)
        lines.put(None)

    threading.Thread(target=pump, daemon=True).start()
    seen: list[str] = []
    try:
        first = lines.get(timeout=120)  # its first word on stderr: the refusal, or progress
        if first is not None:
            seen.append(first)
        refused = first is not None and first.startswith("error:")
        if not refused and proc.poll() is None:  # it is capturing: one signal must end it
            proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=120)  # the stop bound (2 x 1 s) plus finalizing, on a loaded machine
    finally:
        if proc.poll() is None:
            proc.kill()
    while (line := lines.get(timeout=30)) is not None:
        seen.append(line)
    stderr = "".join(seen)
    assert "Traceback" not in stderr, stderr
    if proc.returncode == 2:
        errors = [ln for ln in stderr.splitlines() if ln.startswith("error:")]
        assert len(errors) == 1, stderr
        assert expect in errors[0], stderr
        assert not out.exists() or not list(out.glob("*.h5"))
    else:
        assert proc.returncode == 128 + signal.SIGTERM, stderr
        (take,) = out.glob("*.h5")
        with h5py.File(take) as f:
            assert f.attrs["status"] == "complete"


# -- a stop that does not return, and a clean stop --------------------------------------------------
@pytest.fixture
def stuck_backend() -> Iterator[threading.Event]:
    """`stuck://` cameras: sim cameras whose stop() blocks until the test lets it go (a driver
    stuck in a wait)."""
    release = threading.Event()

    def open_stuck(spec: DeviceSpec) -> Any:
        cam = open_sim_camera(DeviceSpec.parse(spec.raw.replace("stuck://", "sim://", 1)))
        real_stop = cam.stop

        def stop() -> None:
            release.wait()
            real_stop()

        cam.stop = stop  # type: ignore[method-assign]
        return cam

    registry.register_backend("rgb_camera", "stuck", open_stuck)
    yield release
    release.set()
    registry._registered.pop(("rgb_camera", "stuck"), None)


def _wait_pulses(session: CaptureSession, n: int) -> None:
    deadline = time.monotonic() + 240
    while session.progress().pulses < n:
        assert not session.done, session.error
        assert time.monotonic() < deadline, "no pulses within the deadline"
        session.wait(0.05)


@pytest.mark.slow
def test_a_device_whose_stop_never_returns_does_not_hold_the_take(
    tmp_path: Path, stuck_backend: threading.Event
) -> None:
    world = f"stuck-{uuid.uuid4().hex[:8]}"
    cfg = _small_rig(world, stop_backlog_s=1.0)
    cfg.cameras[0].spec = cfg.cameras[0].spec.replace("sim://", "stuck://", 1)
    session = CaptureSession(cfg, tmp_path)
    session.start()
    try:
        _wait_pulses(session, 10)
        session.request_stop("test")
        result = session.wait(240)
    finally:
        stuck_backend.set()
        reset_world(world)
    assert result is not None
    assert session.stop_wait is not None
    assert session.stop_wait.stuck == ("cam0",)
    with Take(result.path) as take:
        assert take.status == "complete"
        assert take.sync_report is not None
        assert any(
            rec.device == "cam0" and "stop did not return" in rec.reason for rec in take.sync_report.losses
        )


@pytest.mark.slow
@pytest.mark.parametrize("how", ["stop", "duration"])
def test_a_clean_stop_records_no_loss_and_does_not_wait_out_the_bound(tmp_path: Path, how: str) -> None:
    world = f"clean-{uuid.uuid4().hex[:8]}"
    session = CaptureSession(
        _small_rig(world, stop_backlog_s=600.0), tmp_path, duration_s=None if how == "stop" else 0.5
    )
    session.start()
    try:
        if how == "stop":
            _wait_pulses(session, 10)
            session.request_stop("test")
        result = session.wait(300)
    finally:
        reset_world(world)
    assert result is not None
    wait = session.stop_wait
    assert wait is not None
    assert wait.all_delivered, wait
    assert wait.behind == (), wait
    assert wait.stuck == (), wait
    with Take(result.path) as take:
        assert take.status == "complete"
        assert take.sync_report is not None
        assert take.sync_report.losses == [], take.sync_report.losses


def _one_line_refusal(result: Any, words: list[str]) -> None:
    assert result.exit_code == 2, (result.exit_code, result.output, result.exception)
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    assert "Traceback" not in result.output
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error:"), result.stderr
    flat = " ".join(result.stderr.split())
    for word in words:
        assert word in flat, (word, flat)
