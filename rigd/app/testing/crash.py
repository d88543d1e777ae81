"""A writer as the crash tests' synthetic rig has it (one 6x8 camera, one 64x48 event sensor
with trigger-in edges at the pulses), the data the rig delivers for each pulse, and the takes
it leaves: unfinished after n steps, or what the first n steps should read back as.

The rig's clock relation is exactly known (device time = rig time + a constant per device;
pulses every PERIOD us), so the rig times of a recovered take can be asserted exactly. The
recovery, damaged-take, failed-take and recovery-on-start tests share it; a writer killed in
a subprocess imports it there. The rig config stamped into the take is the app's `RigConfig`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from rigd.app.config import CameraConfig, EventSensorConfig, RigConfig, TriggerConfig
from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.events import EventArray, EventPacket, TriggerEvents
from rigd.core.frames import Frame
from rigd.core.schema import LossRecord, SyncReport
from rigd.core.settings import TriggerSettings, WriterConfig
from rigd.core.timebase import ClockMap
from rigd.evt import StreamDecoder, encode
from rigd.take import Take, TakeWriter, validate_take

W, H = 64, 48
CAM_SHAPE = (6, 8)
PERIOD = 33_333
RIG0 = 5_000_000  # rig time of pulse 0
OFF_EV = 1_234_567  # ev0 device time = rig time + OFF_EV
OFF_CAM = 777_001  # cam0 device time = rig time + OFF_CAM
HOST0 = 10**12  # host monotonic ns at rig time 0
EV_PER_STEP = 300
CHUNK = 1024
WRITER_CFG = WriterConfig(event_chunk=CHUNK, event_compression="lz4")


def rig_config_json() -> str:
    return RigConfig(
        name="crash-rig",
        trigger=TriggerConfig(spec="sim://t/trigger", settings=TriggerSettings(rate_hz=1e6 / PERIOD)),
        cameras=[CameraConfig(name="cam0", spec="sim://t/cam0")],
        event_sensors=[EventSensorConfig(name="ev0", spec="sim://t/ev0")],
        writer=WRITER_CFG,
    ).model_dump_json()


def open_writer(
    path: Path,
    flush_interval_s: float | None = 0.2,
    *,
    config: WriterConfig = WRITER_CFG,
    evt_format: str | None = None,
) -> TakeWriter:
    """The test rig's writer; `evt_format`: its event sensor's packets carry EVT words."""
    w = TakeWriter(
        path,
        rig_config_json=rig_config_json(),
        take_id=path.stem,
        config=config,
        rigd_version="test",
        flush_interval_s=flush_interval_s,
    )
    w.add_trigger(DeviceInfo(kind="trigger", spec="sim://t/trigger"))
    w.add_camera("cam0", DeviceInfo(kind="rgb_camera", spec="sim://t/cam0"), CAM_SHAPE, np.uint8, "{}")
    w.add_event_sensor("ev0", DeviceInfo(kind="event_sensor", spec="sim://t/ev0"), W, H, "{}", evt_format)
    return w


@dataclass(frozen=True)
class Step:
    """Everything the rig delivers for pulse k."""

    pulse: PulseBatch
    frame: Frame
    events: EventArray
    triggers: TriggerEvents
    packet_host_ns: int


def step(k: int) -> Step:
    rig = RIG0 + k * PERIOD
    host = HOST0 + rig * 1000 + 300_000  # 0.3 ms after the pulse
    img = np.full(CAM_SHAPE, k % 251, np.uint8)
    img[0, 0] = k // 251 % 256
    rng = np.random.default_rng(k)
    t = rig + OFF_EV + np.sort(rng.integers(0, PERIOD, EV_PER_STEP))
    ev = EventArray.from_arrays(
        rng.integers(0, W, EV_PER_STEP), rng.integers(0, H, EV_PER_STEP), rng.integers(0, 2, EV_PER_STEP), t
    )
    trig_t = np.array([rig + OFF_EV, rig + OFF_EV + 1000], np.int64)
    return Step(
        PulseBatch(np.array([k], np.int64), np.array([rig], np.int64), np.array([host], np.int64)),
        Frame(img, rig + OFF_CAM, 5000, k, host + 2_000_000),
        ev,
        TriggerEvents(trig_t, np.array([1, 0], np.uint8), np.zeros(2, np.uint8)),
        host + 1_000_000,
    )


def append_step(w: TakeWriter, k: int) -> None:
    s = step(k)
    w.append_pulses(s.pulse)
    w.append_frame("cam0", s.frame)
    w.append_events("ev0", s.events)
    w.append_triggers("ev0", s.triggers, s.packet_host_ns)


def journal(k: int) -> dict[str, object]:
    return {
        "losses": [LossRecord(device="ev0", what="events", count=k, reason="test: queue full").model_dump()],
        "device_counters": {"ev0": {"delivered": k * EV_PER_STEP}},
        "failed_devices": {},
        "trigger_link": {"corrupt_lines": 1},
        "warnings": [f"flushed after step {k}"],
    }


@dataclass
class Expected:
    """The first n steps, concatenated, in device time."""

    pulse_t: np.ndarray
    frame_t: np.ndarray
    images: np.ndarray
    ev: EventArray
    trig_t: np.ndarray
    trig_host: np.ndarray


def expected(n: int) -> Expected:
    steps = [step(k) for k in range(n)]
    return Expected(
        np.array([s.pulse.t_us[0] for s in steps], np.int64),
        np.array([s.frame.t_exposure_start_us for s in steps], np.int64),
        np.stack([s.frame.image for s in steps]) if steps else np.empty((0, *CAM_SHAPE), np.uint8),
        EventArray.concatenate([s.events for s in steps]),
        np.concatenate([s.triggers.t for s in steps]) if steps else np.empty(0, np.int64),
        np.repeat([s.packet_host_ns for s in steps], 2).astype(np.int64),
    )


# -- unfinished takes ---------------------------------------------------------------------
N_STEPS = 120
MAPS = {"cam0": ClockMap(OFF_CAM, 0), "ev0": ClockMap(OFF_EV, 0)}


def report(n: int) -> SyncReport:
    return SyncReport(
        rate_hz=1e6 / PERIOD, n_pulses=n, t_first_pulse_us=RIG0, t_last_pulse_us=RIG0 + (n - 1) * PERIOD
    )


def unfinished(path: Path, n: int = N_STEPS) -> Path:
    """A take as a writer killed after n steps and one flush leaves it (never finalized)."""
    w = open_writer(path)
    for k in range(n):
        append_step(w, k)
    w.flush(journal=journal(n))
    w.close()
    return path


# -- a sensor that delivers EVT words ------------------------------------------------------
WORDS_CFG = WriterConfig(event_storage="evt_words", fsync=False)


def open_words_writer(path: Path) -> TakeWriter:
    return open_writer(path, config=WORDS_CFG, evt_format="evt3")


def step_bytes(k: int) -> bytes:
    s = step(k)
    return encode("evt3", s.events, s.triggers)


def append_words_step(w: TakeWriter, dec: StreamDecoder, k: int) -> None:
    s = step(k)
    w.append_pulses(s.pulse)
    w.append_frame("cam0", s.frame)
    got, chunk = dec.feed_chunk(step_bytes(k))
    w.append_packet("ev0", EventPacket(got.events, got.triggers, s.packet_host_ns, chunk))


# -- files in a take directory that are no take ---------------------------------------------
def _zero(p: Path) -> None:
    p.write_bytes(b"")


def _random(p: Path) -> None:
    p.write_bytes(np.random.default_rng(7).integers(0, 256, 4096, dtype=np.uint8).tobytes())


def _text(p: Path) -> None:
    p.write_text("this is not an HDF5 file\n" * 50)


def _hdf5_signature_then_junk(p: Path) -> None:
    p.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(range(256)) * 8)


def _truncated_take(p: Path) -> None:
    """A take cut to its first half: the header opens, its attributes do not read."""
    full = p.with_suffix(".full")
    with h5py.File(full, "w") as f:
        f.attrs["schema"] = "rigd.take"
        f.attrs["status"] = "recording"
        f["x"] = np.arange(100_000)
    data = full.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    full.unlink()


def _truncated_real_take(p: Path) -> None:
    """A real unfinished take cut far below its last flush (not the zero-padded kind)."""
    unfinished(p, n=5)
    data = p.read_bytes()
    p.write_bytes(data[:2048])


#: Files in a take directory that are no readable take, by kind: each maker writes one at a path.
BAD: dict[str, Callable[[Path], None]] = {
    "zero": _zero,
    "random": _random,
    "text": _text,
    "signature": _hdf5_signature_then_junk,
    "truncated": _truncated_take,
    "truncated_take": _truncated_real_take,
}


def check_recovered(path: Path, n_flushed: int) -> None:
    """A sealed take: valid, readable, at least what was flushed, and exact rig times."""
    assert validate_take(path) == []
    with Take(path) as take:
        assert take.status == "complete"
        assert take.time_domain == "rig"
        assert take.recovered_utc is not None
        rep = take.recovery_report
        assert rep is not None
        assert rep["outcome"] == "sealed"
        n_frames = len(take.camera("cam0"))
        n_ev = take.sensor("ev0").count
        n_pulses = len(take.pulses())
        assert n_frames >= n_flushed
        assert n_pulses >= n_flushed
        assert n_ev >= n_flushed * EV_PER_STEP
        exp = expected(max(n_frames, n_pulses, -(-n_ev // EV_PER_STEP)))
        ev = take.sensor("ev0").events()
        np.testing.assert_array_equal(ev.t, exp.ev.t[:n_ev] - OFF_EV)
        np.testing.assert_array_equal(ev.x, exp.ev.x[:n_ev])
        np.testing.assert_array_equal(ev.p, exp.ev.p[:n_ev])
        fs = take.camera("cam0")
        np.testing.assert_array_equal(fs.timestamps_us, exp.frame_t[:n_frames] - OFF_CAM)
        assert [fs[i].pulse_index for i in (0, n_frames - 1)] == [0, n_frames - 1]
        tr = take.sensor("ev0").triggers
        np.testing.assert_array_equal(tr.t, exp.trig_t[: len(tr)] - OFF_EV)
        np.testing.assert_array_equal(take.pulses().t_us, exp.pulse_t[:n_pulses])
        # Windowed reads work like on any finalized take.
        a = RIG0 + 3 * PERIOD
        win = take.sensor("ev0").events(a, a + PERIOD)
        want = exp.ev.t[:n_ev] - OFF_EV
        np.testing.assert_array_equal(win.t, want[(want >= a) & (want < a + PERIOD)])
        report = take.sync_report
        assert report is not None
        # The journal of the last flush made it into the report (it may be one flush newer).
        jl = [r for r in report.losses if r.reason == "test: queue full"]
        assert len(jl) == 1
        assert jl[0].count >= n_flushed
        assert report.device_counters["ev0"]["delivered"] >= n_flushed * EV_PER_STEP
        assert report.trigger_link == {"corrupt_lines": 1}
        assert any("ended by a crash" in r.reason for r in report.losses)
        assert any("ended by a crash" in w for w in report.warnings)
        assert report.devices["ev0"].residual_max_us < 1.0
        assert report.devices["cam0"].residual_max_us < 1.0
