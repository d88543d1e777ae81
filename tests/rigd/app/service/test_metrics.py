"""MetricsExporter: served over real HTTP on an ephemeral port, parsed as Prometheus does."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import urllib.error
import urllib.request
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from prometheus_client.parser import text_string_to_metric_families

from rigd import __version__
from rigd.app.service.metrics import MetricsExporter
from rigd.app.service.protocol import DeviceTelemetry, Fault, TakeSummary, Telemetry
from rigd.app.testing.daemon import REPO, endpoints, small_rig
from rigd.core.errors import ConfigError

TAKE_A = "/var/lib/rigd/takes/take-A.h5"
Samples = dict[tuple[str, tuple[tuple[str, str], ...]], float]


@pytest.fixture
def exporter() -> Iterator[MetricsExporter]:
    exp = MetricsExporter(port=0)
    exp.start()
    try:
        yield exp
    finally:
        exp.close()


def scrape(exp: MetricsExporter) -> Samples:
    with urllib.request.urlopen(f"http://127.0.0.1:{exp.port}/metrics", timeout=5) as resp:
        text = resp.read().decode()
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def val(samples: Samples, name: str, **labels: str) -> float:
    return samples[(name, tuple(sorted(labels.items())))]


def dev(name: str, kind: str, total: int, lost: int = 0, **kw: Any) -> DeviceTelemetry:
    base: dict[str, Any] = {"state": "ok", "rate_hz": 30.0, "reconnects": 0}
    base.update(kw)
    return DeviceTelemetry(name=name, kind=kind, total=total, lost=lost, **base)


def snap(seq: int, **kw: Any) -> Telemetry:
    return Telemetry(seq=seq, time_utc="2024-05-01T12:00:00.000Z", pid=1234, **kw)


def summary_a(**kw: Any) -> TakeSummary:
    base: dict[str, Any] = {
        "path": TAKE_A,
        "status": "complete",
        "frames": {"cam0": 60},
        "events": {"ev0": 2_000_100},
        "bytes_written": 2600,
        "losses": [],
        "warnings": [],
        "residual_rms_us": {"cam0": 1.5, "ev0": 0.8},
    }
    base.update(kw)
    return TakeSummary(**base)


def test_port_zero_reports_the_bound_port_and_serves(exporter: MetricsExporter) -> None:
    assert exporter.port > 0
    assert exporter.url == f"http://127.0.0.1:{exporter.port}/metrics"
    s = scrape(exporter)
    assert val(s, "rigd_up") == 1
    assert val(s, "rigd_state", state="idle") == 0  # exists before the first snapshot
    assert val(s, "rigd_faults", code="disk_full") == 0
    assert ("rigd_build_info", (("version", __version__),)) in s
    assert val(s, "rigd_sdnotify_failures_total") >= 0


def test_snapshots_across_two_takes(exporter: MetricsExporter) -> None:
    exporter.update(snap(1, state="idle", disk_free_bytes=900, disk_total_bytes=1000))
    s = scrape(exporter)
    assert val(s, "rigd_state", state="idle") == 1
    assert val(s, "rigd_take_active") == 0
    assert val(s, "rigd_disk_free_bytes") == 900
    assert val(s, "rigd_disk_total_bytes") == 1000
    a = _take_a_running(exporter)
    idle = _take_a_ended(exporter)
    b = _take_b_running(exporter)

    # Every counter is monotonic across the whole sequence.
    for key, value in a.items():
        if key[0].endswith("_total"):
            assert b[key] >= value, key
            assert idle[key] >= value, key


def _take_a_running(exporter: MetricsExporter) -> Samples:
    """Take A, two snapshots: the per-take numbers, device states and faults of the last."""
    exporter.update(
        snap(
            2,
            state="capturing",
            take=TAKE_A,
            take_elapsed_s=1.0,
            pulses=30,
            bytes_written=1000,
            write_rate_bytes_s=1000.0,
            queue_depth=3,
            queue_capacity=256,
            devices=[
                dev("cam0", "rgb_camera", 30, interval_jitter_us=2.5, last_data_age_s=0.01),
                dev("ev0", "event_sensor", 1_000_000, lost=10, rate_hz=1e6),
                dev("trigger", "trigger", 30),
            ],
        )
    )
    exporter.update(
        snap(
            3,
            state="capturing",
            take=TAKE_A,
            take_elapsed_s=2.0,
            pulses=60,
            bytes_written=2500,
            devices=[
                dev("cam0", "rgb_camera", 58, lost=2, state="reconnecting", reconnects=1),
                dev("ev0", "event_sensor", 2_000_000, lost=10),
                dev("trigger", "trigger", 60),
            ],
            faults=[
                Fault(code="device_reconnecting", device="cam0", message="usb", since_utc="x"),
                Fault(code="queue_full", message="q", since_utc="x"),
                Fault(code="queue_full", message="q", since_utc="x"),
            ],
        )
    )
    a = scrape(exporter)
    assert val(a, "rigd_state", state="capturing") == 1
    assert val(a, "rigd_state", state="idle") == 0
    assert val(a, "rigd_take_active") == 1
    assert val(a, "rigd_take_elapsed_seconds") == 2.0
    assert val(a, "rigd_pulses_total") == 60
    assert val(a, "rigd_written_bytes_total") == 2500
    assert val(a, "rigd_device_items_total", device="cam0", kind="rgb_camera") == 58
    assert val(a, "rigd_device_items_total", device="ev0", kind="event_sensor") == 2_000_000
    assert val(a, "rigd_device_lost_total", device="cam0", kind="rgb_camera") == 2
    assert val(a, "rigd_device_reconnects_total", device="cam0") == 1
    assert val(a, "rigd_device_up", device="cam0") == 0
    assert val(a, "rigd_device_up", device="ev0") == 1
    assert val(a, "rigd_device_state", device="cam0", state="reconnecting") == 1
    assert val(a, "rigd_device_state", device="cam0", state="ok") == 0
    assert val(a, "rigd_queue_depth") == 0
    assert val(a, "rigd_queue_capacity") == 0
    assert val(a, "rigd_faults", code="queue_full") == 2
    assert val(a, "rigd_faults", code="device_reconnecting") == 1
    assert val(a, "rigd_faults", code="disk_low") == 0
    # No jitter / data age in this snapshot: the series is absent, not NaN.
    assert ("rigd_device_interval_jitter_seconds", (("device", "cam0"),)) not in a
    assert ("rigd_device_last_data_age_seconds", (("device", "cam0"),)) not in a
    return a


def _take_a_ended(exporter: MetricsExporter) -> Samples:
    """Take A ends: the counters are topped up from its summary."""
    # Take A ends. As the daemon does it, the next snapshot is idle with zeroed per-take
    # numbers and the take's summary, which holds what was written after the last snapshot.
    summary = summary_a()
    idle_devices = [
        dev("cam0", "rgb_camera", 0, state="idle"),
        dev("ev0", "event_sensor", 0, state="idle"),
        dev("trigger", "trigger", 0, state="idle"),
    ]
    for seq in (4, 5):
        exporter.update(snap(seq, state="idle", devices=idle_devices, takes_completed=1, last_take=summary))
    idle = scrape(exporter)
    assert val(idle, "rigd_take_active") == 0
    assert val(idle, "rigd_take_elapsed_seconds") == 0
    assert val(idle, "rigd_pulses_total") == 60  # no summary for pulses
    assert val(idle, "rigd_written_bytes_total") == 2600  # topped up from the summary
    assert val(idle, "rigd_device_items_total", device="cam0", kind="rgb_camera") == 60
    assert val(idle, "rigd_device_items_total", device="ev0", kind="event_sensor") == 2_000_100
    assert val(idle, "rigd_takes_completed_total") == 1
    assert val(idle, "rigd_last_take_residual_rms_seconds", device="cam0") == pytest.approx(1.5e-6)
    assert val(idle, "rigd_last_take_residual_rms_seconds", device="ev0") == pytest.approx(0.8e-6)
    assert val(idle, "rigd_last_take_bytes") == 2600
    assert val(idle, "rigd_last_take_failed") == 0
    assert val(idle, "rigd_device_state", device="cam0", state="idle") == 1
    return idle


def _take_b_running(exporter: MetricsExporter) -> Samples:
    """Take B, after A: the counters go on from where A left them."""
    # Take B: Telemetry's per-take numbers restart from zero; the counters keep growing.
    exporter.update(
        snap(
            6,
            state="capturing",
            take="take-B",
            take_elapsed_s=0.5,
            pulses=15,
            bytes_written=400,
            devices=[
                dev("cam0", "rgb_camera", 15, interval_jitter_us=3.0),
                dev("ev0", "event_sensor", 500_000, lost=1),
            ],
            takes_completed=1,
            last_take=summary_a(),
        )
    )
    b = scrape(exporter)
    assert val(b, "rigd_pulses_total") == 60 + 15
    assert val(b, "rigd_written_bytes_total") == 2600 + 400
    assert val(b, "rigd_device_items_total", device="cam0", kind="rgb_camera") == 60 + 15
    assert val(b, "rigd_device_items_total", device="ev0", kind="event_sensor") == 2_000_100 + 500_000
    assert val(b, "rigd_device_lost_total", device="ev0", kind="event_sensor") == 10 + 1
    assert val(b, "rigd_device_reconnects_total", device="cam0") == 1  # 1 -> 0 is a reset, not -1
    assert val(b, "rigd_device_interval_jitter_seconds", device="cam0") == pytest.approx(3e-6)
    assert val(b, "rigd_device_up", device="cam0") == 1
    # The trigger vanished from the snapshot: its gauges go, its counters stay.
    assert ("rigd_device_up", (("device", "trigger"),)) not in b
    assert val(b, "rigd_device_items_total", device="trigger", kind="trigger") == 60
    return b


def test_idle_snapshots_showing_final_numbers_do_not_double_count(exporter: MetricsExporter) -> None:
    """A daemon that keeps the finished take's numbers in idle snapshots: counted once."""
    exporter.update(snap(1, state="idle"))
    exporter.update(snap(2, state="capturing", take=TAKE_A, pulses=50, bytes_written=2000))
    for seq in (3, 4):
        exporter.update(
            snap(seq, state="idle", pulses=60, bytes_written=2600, takes_completed=1, last_take=summary_a())
        )
    s = scrape(exporter)
    assert val(s, "rigd_pulses_total") == 60
    assert val(s, "rigd_written_bytes_total") == 2600


def test_take_between_two_snapshots_is_counted_from_its_summary(exporter: MetricsExporter) -> None:
    exporter.update(snap(1, state="idle"))
    exporter.update(snap(2, state="idle", takes_completed=1, last_take=summary_a(status="failed", error="X")))
    exporter.update(snap(3, state="idle", takes_completed=1, last_take=summary_a(status="failed", error="X")))
    s = scrape(exporter)
    assert val(s, "rigd_written_bytes_total") == 2600
    assert val(s, "rigd_device_items_total", device="cam0", kind="rgb_camera") == 60
    assert val(s, "rigd_takes_completed_total") == 1
    assert val(s, "rigd_last_take_failed") == 1


def test_a_summary_older_than_the_exporter_is_not_counted(exporter: MetricsExporter) -> None:
    exporter.update(snap(1, state="idle", takes_completed=3, last_take=summary_a()))
    s = scrape(exporter)
    assert val(s, "rigd_written_bytes_total") == 0
    assert ("rigd_device_items_total", (("device", "cam0"), ("kind", "rgb_camera"))) not in s


def test_new_take_straight_after_another(exporter: MetricsExporter) -> None:
    """No idle snapshot in between: a new take name alone resets the baselines."""
    exporter.update(snap(1, state="capturing", take="t1", pulses=100, bytes_written=10))
    exporter.update(snap(2, state="capturing", take="t2", pulses=150, bytes_written=20))
    s = scrape(exporter)
    assert val(s, "rigd_pulses_total") == 250
    assert val(s, "rigd_written_bytes_total") == 30


@pytest.mark.slow
def test_close_frees_the_port_and_is_idempotent() -> None:
    exp = MetricsExporter(port=0)
    exp.start()
    port = exp.port
    scrape(exp)
    exp.close()
    exp.close()
    with socket.socket() as sock:
        # SO_REUSEADDR tolerates the scrape's TIME_WAIT, not a socket still listening.
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(("127.0.0.1", port))
        sock.listen()
    again = MetricsExporter(port=port)
    with again:
        assert again.port == port
        assert val(scrape(again), "rigd_up") == 1


def test_start_twice_is_an_error(exporter: MetricsExporter) -> None:
    with pytest.raises(RuntimeError, match="already started"):
        exporter.start()


def test_port_taken_raises_naming_the_flag_and_the_key() -> None:
    """A second daemon on the host meets the first one's port: the error says how to move it."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        port = sock.getsockname()[1]
        exp = MetricsExporter(port=port)
        with pytest.raises(ConfigError) as err:
            exp.start()
        exp.close()
    text = str(err.value)
    assert f"cannot serve metrics on 127.0.0.1:{port}: Address already in use" in text
    assert "another rigd daemon" in text
    assert "`rigd serve --metrics-port PORT` (0: any free port, -1: off)" in text
    assert "service.metrics_port" in text


# -- who may scrape (docs/security.md) ----------------------------------------------------------


def _get(url: str, headers: dict[str, str] | None = None) -> int:
    req = urllib.request.Request(url, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=10) as resp:
            return int(resp.status)
    except urllib.error.HTTPError as exc:
        return exc.code


def _token_file(tmp_path: Path, token: str, mode: int = 0o600) -> Path:
    path = tmp_path / "metrics.token"
    path.write_text(token + "\n")
    path.chmod(mode)
    return path


def test_metrics_beyond_loopback_without_a_token_are_refused(tmp_path: Path) -> None:
    with pytest.raises(
        ConfigError, match=r"service\.metrics_host: 0\.0\.0\.0 .*set service\.metrics_token_file"
    ):
        MetricsExporter("0.0.0.0", 0)
    # With a token file it may listen anywhere (not bound here: the test stays on loopback).
    MetricsExporter("0.0.0.0", 0, token_file=_token_file(tmp_path, "x" * 24))


@pytest.mark.slow
def test_metrics_beyond_loopback_stop_rigd_serve_with_one_line(tmp_path: Path, runtime_dir: Path) -> None:
    """Like the control socket's non-private bind: exit 2, one line naming the key, nothing bound."""
    cfg = small_rig(
        f"m-{uuid.uuid4().hex[:6]}",
        metrics_host="0.0.0.0",
        metrics_port=0,
        take_dir=str(tmp_path / "takes"),
        **endpoints(runtime_dir),
    )
    cfg_path = tmp_path / "rig.json"
    cfg_path.write_text(json.dumps(cfg.model_dump(mode="json")))
    r = subprocess.run(
        [sys.executable, "-m", "rigd.app.cli", "serve", "--config", str(cfg_path), "--no-http"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )
    assert r.returncode == 2, r.stdout + r.stderr
    assert "Traceback" not in r.stderr
    assert "service.metrics_host: 0.0.0.0" in r.stderr
    assert "service.metrics_token_file" in r.stderr
    assert not (runtime_dir / "control.sock").exists()


def test_a_token_file_makes_every_scrape_need_the_bearer_token(tmp_path: Path) -> None:
    token = "s3cret-metrics-token-0123456789"
    with MetricsExporter(port=0, token_file=_token_file(tmp_path, token)) as exp:
        assert _get(exp.url) == 401
        assert _get(exp.url, {"Authorization": "Bearer wrong-token-0123456789"}) == 401
        assert _get(exp.url, {"Authorization": f"Basic {token}"}) == 401
        assert _get(exp.url, {"Authorization": f"Bearer {token}"}) == 200


@pytest.mark.parametrize(
    ("token", "mode", "why"),
    [("x" * 24, 0o644, "readable by group or others"), ("short", 0o600, "at least 16 characters")],
)
def test_a_bad_token_file_is_refused_naming_it(tmp_path: Path, token: str, mode: int, why: str) -> None:
    path = _token_file(tmp_path, token, mode)
    with pytest.raises(ConfigError, match=f"service.metrics_token_file: {path}: .*{why}"):
        MetricsExporter(port=0, token_file=path)
    with pytest.raises(ConfigError, match="cannot read it"):
        MetricsExporter(port=0, token_file=tmp_path / "missing")
