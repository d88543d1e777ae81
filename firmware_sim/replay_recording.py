"""What a replay plays from a take, and when: the recorded tracks (`Recording`), the shift between
true and rig time fixed when the box starts (`Timeline`), the map from a recorded rig time back
to a device's own clock (`rig_to_device`), and the one `SimWorld` per take its devices share.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray

from drivers.registry import DeviceSpec
from firmware_sim.world import SimWorld, get_world
from rigd.core.errors import ConfigError, RigdError
from rigd.core.layout import Frames, TriggerEdges, frame_group, trigger_in_group
from rigd.core.pixels import stored_pixel_format
from rigd.core.schema import DeviceSync, SyncReport
from rigd.core.timebase import ClockMap
from rigd.take import Take
from rigd.take.h5file import open_checked

SCHEME = "replay"
#: A device runs at most this many buffers ahead of its reader on virtual time.
VIRTUAL_LEAD = 4


@dataclass(frozen=True, slots=True)
class CameraTrack:
    """One camera's recorded frames (images stay in the file)."""

    name: str
    rig_us: NDArray[np.int64]
    device_us: NDArray[np.int64]
    counter: NDArray[np.int64]
    exposure_us: NDArray[np.int64]
    shape: tuple[int, ...]
    cmap: ClockMap | None
    """The camera's clock map (None for a camera the sync report has no fit for)."""
    pixel_format: str = "rgb8"
    """As recorded; a Bayer mosaic is replayed as it is."""


@dataclass(frozen=True, slots=True)
class SensorTrack:
    """One event sensor's clock map and trigger-in edges (events stay in the file)."""

    name: str
    width: int
    height: int
    cmap: ClockMap
    trig_rig: NDArray[np.int64]
    trig_device: NDArray[np.int64]
    trig_p: NDArray[np.uint8]
    trig_channel: NDArray[np.uint8]
    n_events: int


#: Rig and device times a replay accepts: within +-2^45 us (about 1.1 years of clock), the
#: headroom the sim's own clocks have (`firmware_sim.spec_params.MAX_OFFSET_US`).
MAX_TIME_US = 2**45


#: A device clock runs within +-1000 ppm of the rig clock (crystals: about +-100 ppm).
MAX_RATE_ERROR = 1e-3


#: The longest take a replay plays (the capture's own bound).
MAX_SPAN_US = 7 * 86400 * 10**6


def _clock_map(sync: DeviceSync) -> ClockMap:
    return ClockMap(sync.device_ref_us, sync.rig_ref_us, sync.rate, sync.frac_us)


def check_clock_map(path: Path, sync: DeviceSync, lo_rig: int, hi_rig: int) -> None:
    """A recorded clock fit must map the take's span to device times a device can have: a
    finite rate near 1 and times within +-MAX_TIME_US (an EVT stream is encoded from time 0 on,
    so a device time of 2^62 would be a terabyte of time words)."""
    where = f"replay {path}: the sync report's clock map of {sync.device}"
    if not (math.isfinite(sync.rate) and abs(sync.rate - 1.0) <= MAX_RATE_ERROR):
        raise ConfigError(
            f"{where} has rate {sync.rate!r}; a device clock runs within 1 +- {MAX_RATE_ERROR:g}"
        )
    if not (math.isfinite(sync.frac_us) and abs(sync.frac_us) <= 1.0):
        raise ConfigError(f"{where} has frac_us {sync.frac_us!r}; it is within +-1 us")
    for name, value in (("device_ref_us", sync.device_ref_us), ("rig_ref_us", sync.rig_ref_us)):
        if abs(value) > MAX_TIME_US:
            raise ConfigError(f"{where} has {name} {value}, outside +-{MAX_TIME_US} us")
    span = _clock_map(sync).to_device(np.array([lo_rig, hi_rig], np.int64))
    if np.abs(span).max() > MAX_TIME_US:
        raise ConfigError(
            f"{where} puts the take's span at device times {int(span[0])}..{int(span[1])} us, "
            f"outside +-{MAX_TIME_US} us"
        )


class Recording:
    """What a finalized take holds that a replay needs, read once per world."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            take = Take(path)
        except RigdError as exc:
            raise ConfigError(f"replay {path}: {exc}") from None
        with take:
            if take.time_domain != "rig":
                raise ConfigError(
                    f"replay {path}: the take is not finalized (times still in device clocks); "
                    "run `rigd recover` on it first"
                )
            report = take.sync_report
            if report is None:
                raise ConfigError(f"replay {path}: the take has no sync report")
            self.rate_hz = float(report.rate_hz)
            pulses = take.pulses()
            order = np.argsort(pulses.index, kind="stable")
            self.pulse_index = pulses.index[order]
            self.pulse_t = pulses.t_us[order]
            if self.pulse_index.size == 0:
                raise ConfigError(f"replay {path}: the take has no trigger pulses to replay")
            self._pulses = dict(zip(self.pulse_index.tolist(), self.pulse_t.tolist(), strict=True))
            lo, hi = int(self.pulse_t.min()), int(self.pulse_t.max())
            if max(abs(lo), abs(hi)) > MAX_TIME_US or hi - lo > MAX_SPAN_US:
                raise ConfigError(
                    f"replay {path}: the trigger pulses lie at {lo}..{hi} us; a replay plays pulses "
                    f"within +-{MAX_TIME_US} us spanning at most 7 days"
                )
            if not (math.isfinite(self.rate_hz) and 0 < self.rate_hz <= 10_000):
                raise ConfigError(
                    f"replay {path}: the sync report's rate_hz {self.rate_hz!r} is not 0..10000 Hz"
                )
            margin = round(2e6 / self.rate_hz)  # the take window reaches one period past the pulses
            for fit in report.devices.values():
                check_clock_map(path, fit, lo - margin, hi + margin)
            self.config: dict[str, Any] = take.config
            self.sensors: dict[str, SensorTrack] = {}
            with open_checked(path, "r") as f:  # the structure check again: no file is trusted twice
                self.cameras = {name: self._camera(f, name, report) for name in take.cameras}
                for name in take.event_sensors:
                    sync = report.devices.get(name)
                    if sync is None:
                        raise ConfigError(f"replay {path}: event sensor {name} has no clock fit")
                    series = take.sensor(name)
                    trig, (w, h) = series.triggers, series.geometry
                    self.sensors[name] = SensorTrack(
                        name,
                        w,
                        h,
                        _clock_map(sync),
                        trig.t,
                        np.asarray(f[f"{trigger_in_group(name)}/{TriggerEdges.T_DEVICE}"][...], np.int64),
                        trig.p,
                        trig.channel,
                        series.count,
                    )

    @staticmethod
    def _camera(f: h5py.File, name: str, report: SyncReport) -> CameraTrack:
        g = f[frame_group(name)]
        n = int(g[Frames.IMAGES].shape[0])
        shape = tuple(int(v) for v in g[Frames.IMAGES].shape[1:])
        sync = report.devices.get(name)
        cmap = (
            None if sync is None else ClockMap(sync.device_ref_us, sync.rig_ref_us, sync.rate, sync.frac_us)
        )
        return CameraTrack(
            name,
            np.asarray(g[Frames.T_EXPOSURE_START][:n], np.int64),
            np.asarray(g[Frames.T_EXPOSURE_START_DEVICE][:n], np.int64),
            np.asarray(g[Frames.FRAME_COUNTER][:n], np.int64),
            np.asarray(g[Frames.EXPOSURE][:n], np.int64),
            shape,
            cmap,
            stored_pixel_format(g.attrs, shape, f"replay {f.filename}: /frames/{name}"),
        )

    def pulse_time(self, k: int) -> int | None:
        """Recorded box time of pulse k; a pulse the box log missed is put on the schedule."""
        if k > int(self.pulse_index[-1]):
            return None
        t = self._pulses.get(k)
        if t is None:
            return int(self.pulse_t[0]) + round((k - int(self.pulse_index[0])) * 1e6 / self.rate_hz)
        return int(t)

    def camera(self, name: str) -> CameraTrack:
        if name not in self.cameras:
            raise ConfigError(f"replay {self.path}: no camera {name!r} (cameras: {sorted(self.cameras)})")
        return self.cameras[name]

    def sensor(self, name: str) -> SensorTrack:
        if name not in self.sensors:
            raise ConfigError(
                f"replay {self.path}: no event sensor {name!r} (event sensors: {sorted(self.sensors)})"
            )
        return self.sensors[name]


class Timeline:
    """rig = true + shift, fixed when the replayed box is STARTed."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._shift: float | None = None

    def set(self, shift_us: float) -> None:
        with self._cond:
            self._shift = shift_us
            self._cond.notify_all()

    def wait(self, timeout_s: float) -> float | None:
        """The shift, waiting at most `timeout_s` wall seconds for the START."""
        with self._cond:
            self._cond.wait_for(lambda: self._shift is not None, timeout=timeout_s)
            return self._shift


def rig_to_device(cmap: ClockMap, rig_us: NDArray[np.int64]) -> tuple[NDArray[np.int64], int]:
    """Device times whose rig time through `cmap` is exactly `rig_us`; and how many have none
    (a rate above 1 skips a rig microsecond now and then: those get the nearest)."""
    d = cmap.to_device(rig_us)
    for _ in range(2):
        err = cmap.to_rig(d) - rig_us
        bad = err != 0
        if not bad.any():
            return d, 0
        d[bad] -= np.sign(err[bad])
    return d, int(np.count_nonzero(cmap.to_rig(d) != rig_us))


def clock_reset_param(spec: DeviceSpec) -> bool:
    reset = spec.int_param("clock_reset", 0)
    if reset not in (0, 1):
        raise ConfigError(f"device spec {spec.raw!r}: clock_reset={reset!r} (use 0 or 1)")
    return reset == 1


def reset_base(
    reset: bool, world: SimWorld, name: str, cmap: ClockMap | None, shift: float | None, now: float
) -> int:
    """`clock_reset=1`: a device opened after its replug counts from 0 again, so its recorded
    device times lose the device time of the replug instant; 0 otherwise."""
    fault = world.unplug_fault(name)
    if not reset or cmap is None or shift is None or not fault.replugged_before(now):
        return 0
    return int(cmap.to_device(np.array([round(fault.end_us + shift)], np.int64))[0])


def _take_path(spec: DeviceSpec) -> Path:
    raw = (spec.location + spec.path) if spec.location else spec.path
    path = Path(raw)
    if not path.is_absolute():
        raise ConfigError(f"device spec {spec.raw!r}: the take path must be absolute (replay:///abs/take.h5)")
    if not path.is_file():
        raise ConfigError(f"device spec {spec.raw!r}: no take file at {path}")
    return path


def replay_world(spec: DeviceSpec) -> tuple[SimWorld, Recording, Timeline]:
    """The world of a take's replay (one per take path and process), its recording and timeline."""
    path = _take_path(spec)
    world = get_world(f"replay:{path}", 0, spec.params.get("clock"))
    rec = world.resource("replay_recording", lambda: Recording(path))
    timeline = world.resource("replay_timeline", Timeline)
    assert isinstance(rec, Recording)
    assert isinstance(timeline, Timeline)
    return world, rec, timeline


def device_name(spec: DeviceSpec) -> str:
    """The recorded device a spec replays (its `device` parameter), which it must name."""
    name = spec.params.get("device", "")
    if not name:
        raise ConfigError(f"device spec {spec.raw!r}: say which recorded device to replay (?device=NAME)")
    return name


def buffers_param(spec: DeviceSpec, name: str, default: int) -> int:
    """A replayed device's buffer size parameter: at least one."""
    n = spec.int_param(name, default)
    if n < 1:
        raise ConfigError(f"device spec {spec.raw!r}: {name}={n} must be >= 1")
    return n


def replay_spec(take: Path, device: str, **params: str) -> str:
    """The spec that replays one device of a take."""
    query = "&".join(f"{k}={v}" for k, v in {"device": device, **params}.items())
    return f"{SCHEME}://{take.resolve()}?{query}"
