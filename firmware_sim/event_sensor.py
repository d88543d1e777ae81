"""Simulated event sensor: ideal change-detection pixels watching the scene in real time.

A generator thread wakes every `SLICE_US` of true time and produces the events of the
elapsed interval: the interval is cut into sub-steps short enough that sprites move at
most `MAX_STEP_PX` per sub-step, the log intensity is rendered only inside the boxes that
can change, and a numba kernel (nogil, so two sensors run in parallel) compares it with
each pixel's reference level. A pixel crossing k thresholds in one sub-step emits k events
at times linearly interpolated between the two renders. That is the noise-free case of
`firmware_sim.event_model`; with `pixel_model=full` in the spec the sensor runs that model
(mismatch, noise, refractory, low-pass) on whole rendered frames instead.

The sensor talks like a Prophesee camera: each slice's events and trigger-in edges are
encoded into an EVT 3.0 byte stream (time-ordered, trigger edges interleaved), and the host
side is the production `drivers.evt_stream.EvtStreamSensor`, which decodes it. The generator
runs `GENERATION_LAG_US` behind true time so the trigger box's edges for a slice are latched
before the slice is encoded; an edge later than that cannot be placed in the time-ordered
stream and is counted (`triggers_late`), never dropped silently. Buffers go into a bounded
queue whose overflows are counted.

`unplug_at_s` / `unplug_for_s` take the sensor off the bus (docs/sim-faults.md): `read_bytes`
raises DeviceError, which `EvtStreamSensor.read_events` passes on to the capture pipeline, the
generator stops, and the span of true time whose events the host never got goes into the
ground truth (`GroundTruth.unplugged`).
"""

from __future__ import annotations

import json
import logging
import math
import queue
import threading
import time
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from drivers.base import AcquisitionStats, Capability
from drivers.evt import Evt3Encoder
from drivers.evt_stream import EvtStreamSensor
from drivers.registry import DeviceSpec
from firmware_sim.board_scene import sim_scene
from firmware_sim.event_model import EventSimulator, PixelModelConfig
from firmware_sim.scene import LOG_LUT_SCALE, Scene, View, lin_log, log_lut
from firmware_sim.world import (
    DeviceClock,
    Edge,
    SimWorld,
    Unpluggable,
    UnplugParams,
    get_world,
    power_on_clock,
    truth_journal,
    unplug_params,
)
from rigd.core.devices import DeviceInfo
from rigd.core.errors import ConfigError, DeviceError
from rigd.core.events import EventArray, TriggerEvents
from rigd.core.settings import EventSensorSettings

log = logging.getLogger(__name__)

#: True time between generator wake-ups.
SLICE_US = 5_000
#: Largest sprite motion between two renders, in pixels.
MAX_STEP_PX = 3.0
#: Packets merged into one `read_events` answer at most.
_MAX_MERGE = 64

_CAPABILITIES = frozenset({Capability.TRIGGER_IN, Capability.DEVICE_TIMESTAMPS})


I64 = NDArray[np.int64]
F32 = NDArray[np.float32]


@njit(nogil=True, cache=True, inline="always")
def _emit_pixel(  # pragma: no cover - numba
    lp: float,
    ln: float,
    r: float,
    threshold: float,
    t0: float,
    dt: float,
    x: int,
    y: int,
    c_off: float,
    c_rate: float,
    out_x: NDArray[np.uint16],
    out_y: NDArray[np.uint16],
    out_p: NDArray[np.int8],
    out_t: I64,
    n: int,
) -> tuple[int, float]:
    """Events of one pixel whose log level went lp -> ln in [t0, t0 + dt] with reference r.

    Returns (new n, new reference), or (-1, r) when the output has no room for them.
    Each crossing of r + m * threshold is timed by linear interpolation between lp and ln
    and stamped like DeviceClock.stamp: floor(c_off + t * c_rate).
    """
    d = ln - r
    if -threshold < d < threshold:
        return n, r
    k = int(abs(d) / threshold)
    if n + k > out_x.shape[0]:
        return -1, r
    sign = 1.0 if d > 0 else -1.0
    slope = ln - lp
    for m in range(1, k + 1):
        level = r + sign * m * threshold
        frac = (level - lp) / slope if slope != 0.0 else 1.0
        frac = min(max(frac, 0.0), 1.0)
        out_x[n] = x
        out_y[n] = y
        out_p[n] = 1 if sign > 0 else -1
        out_t[n] = math.floor(c_off + (t0 + frac * dt) * c_rate)
        n += 1
    return n, r + sign * k * threshold


@njit(nogil=True, cache=True)
def generate_events_kernel(  # pragma: no cover - numba
    l_prev: F32,
    l_new: F32,
    ref: F32,
    threshold: float,
    t0: float,
    t1: float,
    x0: int,
    y0: int,
    c_off: float,
    c_rate: float,
    start: int,
    out_x: NDArray[np.uint16],
    out_y: NDArray[np.uint16],
    out_p: NDArray[np.int8],
    out_t: I64,
    n_out: int,
) -> tuple[int, int]:
    """Events of one sub-step [t0, t1] from two log images of a box with top-left (x0, y0).

    The reference `ref` is updated in place. Pixels are visited in raster order from flat
    index `start`; when the outputs are full the kernel stops before the pixel that would
    overflow and returns (n_out, that pixel) so the caller can grow them and resume; it
    returns (n_out, h * w) when done.
    """
    h, w = l_new.shape
    dt = t1 - t0
    for idx in range(start, h * w):
        i = idx // w
        j = idx - i * w
        n, r = _emit_pixel(
            l_prev[i, j],
            l_new[i, j],
            ref[i, j],
            threshold,
            t0,
            dt,
            x0 + j,
            y0 + i,
            c_off,
            c_rate,
            out_x,
            out_y,
            out_p,
            out_t,
            n_out,
        )
        if n < 0:
            return n_out, idx
        n_out = n
        ref[i, j] = r
    return n_out, h * w


@njit(nogil=True, cache=True, inline="always")
def _quad_row_span(q: NDArray[np.float64], y: float) -> tuple[float, float]:  # pragma: no cover - numba
    """x extent of the convex quad q (4, 2) on row y; (inf, -inf) when the row misses it."""
    lo = np.inf
    hi = -np.inf
    for e in range(4):
        xa, ya = q[e, 0], q[e, 1]
        xb, yb = q[(e + 1) % 4, 0], q[(e + 1) % 4, 1]
        if (ya <= y <= yb) or (yb <= y <= ya):
            if ya == yb:
                lo = min(lo, xa, xb)
                hi = max(hi, xa, xb)
            else:
                xe = xa + (y - ya) * (xb - xa) / (yb - ya)
                lo = min(lo, xe)
                hi = max(hi, xe)
    return lo, hi


@njit(nogil=True, cache=True)
def _render_events_kernel(  # pragma: no cover - numba
    bg_int: F32,
    bg_log: F32,
    last_log: F32,
    ref: F32,
    stack: F32,
    texels: I64,
    hinv: NDArray[np.float64],
    quads: NDArray[np.float64],
    lut: F32,
    lut_scale: float,
    threshold: float,
    kmax: int,
    t0: float,
    t1: float,
    c_off: float,
    c_rate: float,
    y_start: int,
    y_end: int,
    out_x: NDArray[np.uint16],
    out_y: NDArray[np.uint16],
    out_p: NDArray[np.int8],
    out_t: I64,
    n_out: int,
) -> tuple[int, int]:
    """Render the log intensity at t1 where sprites are or were, and emit the events since t0.

    Only pixels inside some sprite's quad at t0 or t1 (`quads`: (n, 2, 4, 2) image corners)
    can change, so each row visits just the union of those spans. One fused pass per
    pixel: inverse-map into each covering sprite (bilinear, alpha compositing over the
    background), log through the table, compare with the reference. `last_log` (the log
    image at t0) and `ref` are full-frame and updated in place; uncovered pixels read the
    view's precomputed background log. Rows are atomic: when a row might not fit in the
    outputs, returns (n_out, that row) for the caller to grow them and resume.
    """
    _height, width = bg_int.shape
    n_spr = texels.shape[0]
    dt = t1 - t0
    lut_max = lut.shape[0] - 2.0
    side = stack.shape[1]
    row = side * 2
    flat = stack.reshape(-1)
    lo = np.empty(n_spr, np.int64)
    hi = np.empty(n_spr, np.int64)
    seg_lo = np.empty(n_spr, np.int64)
    seg_hi = np.empty(n_spr, np.int64)
    for y in range(y_start, y_end):
        fy = float(y)
        n_seg = 0
        row_px = 0
        for s in range(n_spr):
            a0, b0 = _quad_row_span(quads[s, 0], fy)
            a1, b1 = _quad_row_span(quads[s, 1], fy)
            a = min(a0, a1)
            b = max(b0, b1)
            if a > b:
                lo[s] = 0
                hi[s] = 0
                continue
            lo[s] = max(math.floor(a), 0)
            hi[s] = min(math.floor(b) + 2, width)
            if hi[s] <= lo[s]:
                continue
            # Insert [lo, hi) into the sorted segment list, merging overlaps.
            pos = n_seg
            while pos > 0 and seg_lo[pos - 1] > lo[s]:
                seg_lo[pos] = seg_lo[pos - 1]
                seg_hi[pos] = seg_hi[pos - 1]
                pos -= 1
            seg_lo[pos] = lo[s]
            seg_hi[pos] = hi[s]
            n_seg += 1
        if n_seg == 0:
            continue
        m = 0
        for i in range(1, n_seg):
            if seg_lo[i] <= seg_hi[m]:
                seg_hi[m] = max(seg_hi[m], seg_hi[i])
            else:
                m += 1
                seg_lo[m] = seg_lo[i]
                seg_hi[m] = seg_hi[i]
        n_seg = m + 1
        for i in range(n_seg):
            row_px += seg_hi[i] - seg_lo[i]
        if n_out + row_px * kmax > out_x.shape[0]:
            return n_out, y
        for i in range(n_seg):
            for x in range(seg_lo[i], seg_hi[i]):
                fx = float(x)
                inten = bg_int[y, x]
                hit = False
                for s in range(n_spr):
                    if x < lo[s] or x >= hi[s]:
                        continue
                    rw = 1.0 / (hinv[s, 2, 0] * fx + hinv[s, 2, 1] * fy + hinv[s, 2, 2])
                    u = (hinv[s, 0, 0] * fx + hinv[s, 0, 1] * fy + hinv[s, 0, 2]) * rw
                    v = (hinv[s, 1, 0] * fx + hinv[s, 1, 1] * fy + hinv[s, 1, 2]) * rw
                    lim = texels[s] - 1
                    if u < 0.0 or v < 0.0 or u >= lim or v >= lim:
                        continue
                    iu = int(u)
                    iv = int(v)
                    fu = u - iu
                    fv = v - iv
                    # Flat indexing: (s, iv, iu, channel) in the C-contiguous stack.
                    b = ((s * side + iv) * side + iu) * 2
                    p00, a00 = flat[b], flat[b + 1]
                    p01, a01 = flat[b + 2], flat[b + 3]
                    p10, a10 = flat[b + row], flat[b + row + 1]
                    p11, a11 = flat[b + row + 2], flat[b + row + 3]
                    top_p = p00 + fu * (p01 - p00)
                    bot_p = p10 + fu * (p11 - p10)
                    top_a = a00 + fu * (a01 - a00)
                    bot_a = a10 + fu * (a11 - a10)
                    pa = top_p + fv * (bot_p - top_p)
                    al = top_a + fv * (bot_a - top_a)
                    inten = inten * (1.0 - al) + pa
                    hit = True
                if hit:
                    f = min(max(inten, 0.0) * lut_scale, lut_max)
                    k = int(f)
                    ln = lut[k] + (f - k) * (lut[k + 1] - lut[k])
                else:
                    ln = bg_log[y, x]
                n_out, r = _emit_pixel(
                    last_log[y, x],
                    ln,
                    ref[y, x],
                    threshold,
                    t0,
                    dt,
                    x,
                    y,
                    c_off,
                    c_rate,
                    out_x,
                    out_y,
                    out_p,
                    out_t,
                    n_out,
                )
                ref[y, x] = r
                last_log[y, x] = ln
    return n_out, y_end


@njit(nogil=True, cache=True)
def sort_events_by_time(  # pragma: no cover - numba
    x: NDArray[np.uint16], y: NDArray[np.uint16], p: NDArray[np.int8], t: I64
) -> tuple[NDArray[np.uint16], NDArray[np.uint16], NDArray[np.int8], I64]:
    """Stable counting sort by time; a slice spans a few thousand microseconds at most."""
    n = t.shape[0]
    ox = np.empty(n, np.uint16)
    oy = np.empty(n, np.uint16)
    op = np.empty(n, np.int8)
    ot = np.empty(n, np.int64)
    if n == 0:
        return ox, oy, op, ot
    tmin = t.min()
    counts = np.zeros(t.max() - tmin + 2, np.int64)
    for i in range(n):
        counts[t[i] - tmin + 1] += 1
    for b in range(1, counts.shape[0]):
        counts[b] += counts[b - 1]
    for i in range(n):
        b = t[i] - tmin
        dst = counts[b]
        counts[b] += 1
        ox[dst] = x[i]
        oy[dst] = y[i]
        op[dst] = p[i]
        ot[dst] = t[i]
    return ox, oy, op, ot


class EventBuffer:
    """Growable struct-of-arrays the kernels write into (times already device stamps)."""

    def __init__(self, capacity: int = 1 << 15) -> None:
        self.x = np.empty(capacity, np.uint16)
        self.y = np.empty(capacity, np.uint16)
        self.p = np.empty(capacity, np.int8)
        self.t = np.empty(capacity, np.int64)
        self.n = 0

    def grow(self) -> None:
        cap = 2 * self.x.shape[0]
        for name in ("x", "y", "p", "t"):
            old = getattr(self, name)
            new = np.empty(cap, old.dtype)
            new[: self.n] = old[: self.n]
            setattr(self, name, new)

    def to_array(self) -> EventArray:
        """The events so far, sorted by time (stable)."""
        if self.n == 0:
            return EventArray.empty()
        n = self.n
        return EventArray(*sort_events_by_time(self.x[:n], self.y[:n], self.p[:n], self.t[:n]))


def generate_events(
    scene: Scene,
    view: View,
    last_log: F32,
    ref: F32,
    threshold: float,
    t0_us: float,
    t1_us: float,
    clock: DeviceClock | None = None,
    buf: EventBuffer | None = None,
) -> EventBuffer:
    """Events of [t0, t1], unsorted: updates `last_log` (log image at t0 -> t1) and `ref`.

    Only the boxes that can change are visited; outside them `last_log` stays valid.
    Times are stamped with `clock` (identity when None).
    """
    out = buf if buf is not None else EventBuffer()
    if t1_us <= t0_us or not scene.objects:
        return out
    c_off, c_rate = (clock.offset_us, clock.rate) if clock is not None else (0.0, 1.0)
    n_sub = scene.substeps(view, t0_us, t1_us, MAX_STEP_PX)
    times = np.linspace(t0_us, t1_us, n_sub + 1)
    corners = scene.object_corners(view, times)  # (n_sub + 1, n_obj, 4, 2)
    hinvs = np.linalg.inv(scene.object_homographies(view, times[1:]))
    y_lo = max(math.floor(corners[..., 1].min()), 0)
    y_hi = min(math.floor(corners[..., 1].max()) + 2, view.height)
    # Log range of the scene is below 4 (lin_log(0) ~ 2.0, log(256) ~ 5.6).
    kmax = int(4.0 / threshold) + 1
    for k in range(n_sub):
        if y_hi <= y_lo:
            break
        quads = np.ascontiguousarray(np.stack([corners[k], corners[k + 1]], axis=1))
        hinv = np.ascontiguousarray(hinvs[k])
        y = y_lo
        while True:
            out.n, y = _render_events_kernel(
                view.bg_intensity,
                view.bg_log,
                last_log,
                ref,
                scene.sprite_stack,
                scene.sprite_texels,
                hinv,
                quads,
                _LUT,
                LOG_LUT_SCALE,
                threshold,
                kmax,
                float(times[k]),
                float(times[k + 1]),
                c_off,
                c_rate,
                y,
                y_hi,
                out.x,
                out.y,
                out.p,
                out.t,
                out.n,
            )
            if y >= y_hi:
                break
            out.grow()
    return out


_LUT = log_lut()


@dataclass(frozen=True, slots=True)
class SensorParams:
    """What an event sensor spec may set."""

    width: int = 1280
    height: int = 720
    threshold: float = 0.3
    buffer_packets: int = 1024
    pixel_model: PixelModelConfig | None = None
    """None: the fast ideal kernel (rendering only what moves). Otherwise the full pixel model
    of `firmware_sim.event_model` (noise, mismatch, refractory, low-pass) on whole rendered log
    frames at every sub-step: real time only at small resolutions."""
    unplug: UnplugParams | None = None


@dataclass(frozen=True, slots=True)
class _Packet:
    """One slice's EVT buffer, with what the ground truth and the journal need to know of it."""

    payload: bytes
    host_ns: int
    n_events: int
    n_triggers: int
    t_first_us: int
    """Device time of the first event (0 when there is none)."""
    t_last_us: int
    true_end_us: float
    """True time the slice ends: the host has every event before it once it read this packet."""


#: How far behind true time the generator encodes, so trigger edges are in before their slice.
GENERATION_LAG_US = 50_000


class SimEventSensor(Unpluggable):
    """An ideal event sensor in a `SimWorld`, with its own drifting clock and trigger-in.

    A `drivers.evt_stream.ByteSource`: it hands out EVT 3.0 buffers, as a camera would.
    """

    _device_label = "event sensor"

    def __init__(
        self,
        world: SimWorld,
        name: str,
        scene: Scene,
        clock: DeviceClock,
        params: SensorParams | None = None,
        spec: str = "",
    ) -> None:
        p = params or SensorParams()
        if p.threshold <= 0:
            raise ConfigError(f"event sensor {name}: threshold must be > 0, got {p.threshold}")
        if p.buffer_packets < 1:
            raise ConfigError(f"event sensor {name}: buffer_packets must be >= 1, got {p.buffer_packets}")
        if not (0 < p.width <= 65535 and 0 < p.height <= 65535):
            raise ConfigError(f"event sensor {name}: bad geometry {p.width}x{p.height}")
        self._world, self._name, self._scene, self._clock, self._p = world, name, scene, clock, p
        self._view = scene.view(name, p.width, p.height)
        self._info = DeviceInfo(
            kind="event_sensor",
            spec=spec or f"sim://{world.name}/{name}",
            vendor="rigd-sim",
            model="SimEventSensor",
            serial=f"{world.name}/{name}",
            firmware="sim-1",
            facts={"evt_format": "evt3", "pixel_model": "ideal", "threshold": str(p.threshold)},
        )
        self._settings = EventSensorSettings()
        self._fault = world.unplug_fault(name)
        self._fault.check_present(self._info.spec)
        self._opened_us = world.now_us()
        self._unplug_noted = False
        self._delivered_until_us = -math.inf
        self._journal = truth_journal()
        self._journal_head = f'{{"world":{json.dumps(world.name)},"dev":{json.dumps(name)},"kind":"events"'
        world.register_clock(name, clock)
        self._lock = threading.Lock()
        self._accepting = False
        self._pending: list[tuple[float, int]] = []
        self._packets: queue.Queue[_Packet] = queue.Queue(maxsize=p.buffer_packets)
        self._encoder = Evt3Encoder()
        self._encoded_until_us = -math.inf
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._closed = False
        self._events_lost = 0
        self._model_t = 0
        self._counts = {
            "packets_dropped": 0,
            "triggers_dropped": 0,
            "triggers_late": 0,
            "events_generated": 0,
            "triggers": 0,
            "bytes": 0,
            "packets_lost_unplugged": 0,
        }
        self._unsubscribe = world.wire.subscribe(self._on_edge)
        self._unlisten = self._fault.listen(self._on_unplug)

    # --- Device ---------------------------------------------------------------------------

    @property
    def info(self) -> DeviceInfo:
        return self._info

    @property
    def capabilities(self) -> frozenset[Capability]:
        return _CAPABILITIES

    @property
    def geometry(self) -> tuple[int, int]:
        return self._p.width, self._p.height

    @property
    def evt_format(self) -> str:
        return "evt3"

    @property
    def clock(self) -> DeviceClock:
        return self._clock

    def configure(self, settings: EventSensorSettings) -> None:
        self._check_alive()
        if self._thread is not None:
            raise DeviceError(f"event sensor {self._name}: configure while started; stop it first")
        self._settings = settings.model_copy()

    def start(self) -> None:
        self._check_alive()
        if self._thread is not None:
            raise DeviceError(f"event sensor {self._name} is already started")
        if self._settings.sync_mode == "slave":
            # A slave counts time on its master's clock (the sync cable): share that clock.
            master = self._settings.sync_master
            clocks = self._world.truth.clocks
            if master is None or master not in clocks:
                raise ConfigError(
                    f"event sensor {self._name}: sync master {master!r} is not a device of world "
                    f"{self._world.name!r} (sim device names must match the rig names)"
                )
            self._clock = clocks[master]
            self._world.register_clock(self._name, self._clock)
        t_start = self._world.now_us()
        last_log = lin_log(self._scene.render_intensity(self._view, t_start))
        self._stop.clear()
        self._error = None
        with self._lock:
            self._pending.clear()
            self._accepting = True
            self._delivered_until_us = t_start
        self._thread = threading.Thread(
            target=self._run, args=(t_start, last_log), name=f"sim-events-{self._name}", daemon=True
        )
        self._thread.start()
        self._arm_unplug(self._p.unplug, t_start, lost_frames_on_edges=False)
        log.info("event sensor %s started at true %.0f us", self._name, t_start)

    def stop(self) -> None:
        with self._lock:
            self._accepting = False
        thread, self._thread = self._thread, None
        if thread is None:
            return
        self._stop.set()
        thread.join()
        log.info("event sensor %s stopped; %s", self._name, self.stats())
        if self._error is not None:
            raise DeviceError(
                f"event sensor {self._name}: generator failed: {self._error!r}"
            ) from self._error

    def close(self) -> None:
        if self._closed:
            return
        try:
            self.stop()
        finally:
            self._unsubscribe()
            self._unlisten()
            self._closed = True

    def read_bytes(self, timeout_s: float) -> tuple[bytes, int] | None:
        self._check_alive()
        try:
            first = (
                self._packets.get(timeout=max(timeout_s, 0.0))
                if timeout_s > 0
                else self._packets.get_nowait()
            )
        except queue.Empty:
            return None
        parts = [first]
        while len(parts) < _MAX_MERGE:
            try:
                parts.append(self._packets.get_nowait())
            except queue.Empty:
                break
        with self._lock:
            if self._dead(self._world.now_us()):  # unplugged while we waited: these are lost too
                self._note_unplug_locked(parts)
                raise self._unplugged_error()
            self._delivered_until_us = parts[-1].true_end_us
        if self._journal is not None:
            self._write_journal(parts)
        return b"".join(pk.payload for pk in parts), parts[-1].host_ns

    def _write_journal(self, parts: list[_Packet]) -> None:
        """One line per buffer handed to the reader (a decoded `EventPacket`), never per event."""
        n = sum(pk.n_events for pk in parts)
        with_events = [pk for pk in parts if pk.n_events]
        first = str(with_events[0].t_first_us) if with_events else "null"
        last = str(with_events[-1].t_last_us) if with_events else "null"
        n_trig = sum(pk.n_triggers for pk in parts)
        assert self._journal is not None
        self._journal.write(
            f'{self._journal_head},"n":{n},"n_triggers":{n_trig},"t_first_device_us":{first},'
            f'"t_last_device_us":{last},"host_time_ns":{time.monotonic_ns()}}}'
        )

    def stats(self) -> AcquisitionStats:
        with self._lock:
            return AcquisitionStats(
                delivered=self._counts["events_generated"] - self._events_lost,
                device_dropped=self._events_lost,
                extra=dict(self._counts),
            )

    def _check_open(self) -> None:
        if self._closed:
            raise DeviceError(f"event sensor {self._name} is closed")

    # --- unplug fault ---------------------------------------------------------------------

    def _note_unplug_locked(self, lost: list[_Packet]) -> None:
        """Log what the unplug cost (caller holds the lock); safe to call more than once.

        Everything after the last slice the host read is lost: packets still queued, the
        slices the generator (running behind true time) had not encoded yet, and the window.
        """
        lost = list(lost)
        while True:
            try:
                lost.append(self._packets.get_nowait())
            except queue.Empty:
                break
        n_lost = sum(pk.n_events for pk in lost)
        self._events_lost += n_lost
        self._counts["packets_lost_unplugged"] += len(lost)
        if not self._unplug_noted:
            self._unplug_noted = True
            self._accepting = False
            if self._thread is not None:
                self._world.truth.add_unplugged(self._name, self._delivered_until_us, self._fault.end_us)
            log.warning(
                "event sensor %s unplugged; events after true %.0f us lost",
                self._name,
                self._delivered_until_us,
            )

    # --- trigger-in -----------------------------------------------------------------------

    def _on_edge(self, edge: Edge) -> None:
        """Runs on the trigger box's thread: only latch the edge."""
        with self._lock:
            if not (self._accepting and self._settings.enable_trigger_in) or self._dead(edge.true_us):
                return
            if edge.true_us < self._encoded_until_us:
                self._counts["triggers_late"] += 1
                log.warning(
                    "event sensor %s: trigger edge at true %.0f us arrived after its slice was encoded",
                    self._name,
                    edge.true_us,
                )
                return
            self._pending.append((edge.true_us, 1 if edge.rising else 0))

    def _take_triggers(self, t_end_us: float | None) -> TriggerEvents:
        """Pending edges before `t_end_us` (all of them when None), stamped in the sensor clock."""
        with self._lock:
            self._pending.sort()
            if t_end_us is None:
                taken, self._pending = self._pending, []
            else:
                n = 0
                while n < len(self._pending) and self._pending[n][0] < t_end_us:
                    n += 1
                taken, self._pending = self._pending[:n], self._pending[n:]
        if not taken:
            return TriggerEvents.empty()
        t = np.array([self._clock.stamp(tu) for tu, _ in taken], np.int64)
        pol = np.array([p for _, p in taken], np.uint8)
        ch = np.full(len(taken), self._settings.trigger_in_channel, np.uint8)
        return TriggerEvents(t, pol, ch)

    # --- generator ------------------------------------------------------------------------

    def _model_events(self, model: EventSimulator, t0: float, t1: float) -> EventArray:
        """Full pixel model: whole log frames at sub-steps of at most MAX_STEP_PX of motion."""
        n_sub = self._scene.substeps(self._view, t0, t1, MAX_STEP_PX)
        parts = []
        for t in np.linspace(t0, t1, n_sub + 1)[1:]:
            ti = round(t)
            if ti <= self._model_t:
                continue
            parts.append(model.step(lin_log(self._scene.render_intensity(self._view, t)), ti))
            self._model_t = ti
        ev = EventArray.concatenate(parts)
        # Model times are true-time microseconds: latch them on the sensor's own clock.
        t_dev = np.floor(self._clock.offset_us + ev.t.astype(np.float64) * self._clock.rate).astype(np.int64)
        return ev.with_time(t_dev)

    def _run(self, t_start: float, last_log: NDArray[np.float32]) -> None:
        ref = last_log.copy()
        model: EventSimulator | None = None
        if self._p.pixel_model is not None:
            model = EventSimulator(self._p.width, self._p.height, self._p.pixel_model)
            self._model_t = round(t_start)
            model.step(last_log, self._model_t)
        t_prev = t_start
        try:
            while True:
                wake = t_prev + SLICE_US + GENERATION_LAG_US
                stopping = self._stop.wait(max(0.0, (wake - self._world.now_us()) * 1e-6))
                if self._dead(self._world.now_us()):
                    with self._lock:
                        self._note_unplug_locked([])
                    return  # no power, no events; stop() finds no error
                # At stop everything up to now goes out: no later edge can belong to it.
                t_now = self._world.now_us() - (0 if stopping else GENERATION_LAG_US)
                if t_now <= t_prev and not stopping:
                    continue
                if model is not None:
                    events = self._model_events(model, t_prev, t_now)
                else:
                    buf = generate_events(
                        self._scene, self._view, last_log, ref, self._p.threshold, t_prev, t_now, self._clock
                    )
                    events = buf.to_array()
                with self._lock:
                    self._encoded_until_us = t_now
                triggers = self._take_triggers(None if stopping else t_now)
                self._emit(events, triggers, t_now)
                t_prev = t_now
                if stopping:
                    return
        except Exception as exc:  # the thread must not die silently: stop() re-raises it
            log.exception("event sensor %s: generator failed", self._name)
            self._error = exc

    def _emit(self, events: EventArray, triggers: TriggerEvents, true_end_us: float) -> None:
        if len(events) == 0 and len(triggers) == 0:
            return
        payload = self._encoder.encode(events, triggers)
        n = len(events)
        packet = _Packet(
            payload,
            time.monotonic_ns(),
            n,
            len(triggers),
            int(events.t.min()) if n else 0,
            int(events.t.max()) if n else 0,
            true_end_us,
        )
        with self._lock:
            # Under the lock, so an unplug noted meanwhile finds this packet queued or not at all.
            if self._dead(self._world.now_us()):
                self._note_unplug_locked([packet])
                full = False
            else:
                try:
                    self._packets.put_nowait(packet)
                    full = False
                except queue.Full:
                    full = True
        if full:
            with self._lock:
                self._events_lost += len(events)
                self._counts["packets_dropped"] += 1
                self._counts["triggers_dropped"] += len(triggers)
            log.warning(
                "event sensor %s: buffer full, dropped a packet of %d events, %d triggers",
                self._name,
                len(events),
                len(triggers),
            )
        with self._lock:
            self._counts["events_generated"] += len(events)
            self._counts["triggers"] += len(triggers)
            self._counts["bytes"] += len(payload)


#: Spec parameters of the full pixel model -> PixelModelConfig fields.
_MODEL_PARAMS = {
    "sigma": "sigma",
    "threshold_on": "threshold_on",
    "threshold_off": "threshold_off",
    "refractory_us": "refractory_us",
    "leak_hz": "leak_rate_hz",
    "shot_hz": "shot_noise_rate_hz",
    "hot_fraction": "hot_pixel_fraction",
    "lowpass_hz": "lowpass_cutoff_hz",
}


def _pixel_model(spec: DeviceSpec, seed: int) -> PixelModelConfig | None:
    kind = spec.param("pixel_model", "ideal")
    given = {k: v for k, v in _MODEL_PARAMS.items() if k in spec.params}
    if kind == "ideal":
        if given:
            raise ConfigError(f"device spec {spec.raw!r}: {', '.join(sorted(given))} need pixel_model=full")
        return None
    if kind != "full":
        raise ConfigError(f"device spec {spec.raw!r}: pixel_model={kind!r}; use ideal or full")
    fields: dict[str, object] = {"input_kind": "log", "threshold": spec.float_param("threshold", 0.3)}
    for key, field_name in given.items():
        fields[field_name] = spec.float_param(key, 0.0)
    if "lowpass_hz" in given:
        fields["lowpass"] = True
    fields["seed"] = seed
    try:
        return PixelModelConfig.model_validate(fields)
    except ValueError as exc:
        raise ConfigError(f"device spec {spec.raw!r}: {exc}") from None


def open_sim_event_sensor(spec: DeviceSpec) -> EvtStreamSensor:
    """Factory for `sim://<world>/<name>?offset_us=&drift_ppm=&seed=&width=&height=&threshold=&buffer_packets=&scene=sprites|board`.

    Fault switches: `unplug_at_s=`, `unplug_for_s=`, `clock_reset=1` (docs/sim-faults.md).
    """
    spec.check_params(
        {"offset_us", "drift_ppm", "seed", "width", "height", "threshold", "buffer_packets", "scene"}
        | {"pixel_model", *_MODEL_PARAMS, "unplug_at_s", "unplug_for_s", "clock_reset"}
    )
    name = spec.path.strip("/")
    if not name:
        raise ConfigError(f"device spec {spec.raw!r}: no device name in the path (sim://<world>/<name>)")
    seed = spec.int_param("seed", 0)
    world = get_world(spec.location or "default", seed)
    scene = sim_scene(spec, world, seed)
    params = SensorParams(
        width=spec.int_param("width", 1280),
        height=spec.int_param("height", 720),
        threshold=spec.float_param("threshold", 0.3),
        buffer_packets=spec.int_param("buffer_packets", 1024),
        pixel_model=_pixel_model(spec, seed),
        unplug=unplug_params(spec),
    )
    for field_name, ok in (
        ("width", 0 < params.width <= 65535),
        ("height", 0 < params.height <= 65535),
        ("threshold", params.threshold > 0 and math.isfinite(params.threshold)),
        ("buffer_packets", params.buffer_packets >= 1),
    ):
        if not ok:
            raise ConfigError(
                f"device spec {spec.raw!r}: {field_name}={spec.params[field_name]!r} out of range"
            )
    clock = DeviceClock(spec.float_param("offset_us", 0.0), spec.float_param("drift_ppm", 0.0))
    clock = power_on_clock(spec, world, name, clock)
    return EvtStreamSensor(SimEventSensor(world, name, scene, clock, params, spec.raw))
