"""The ideal event pixel as numba kernels, and the renderer that feeds them only what moves.

`generate_events` cuts an interval into sub-steps short enough that sprites move at most
`MAX_STEP_PX` per sub-step (and none longer than `MAX_STEP_US`), renders the log intensity
only inside the boxes that can change, and compares it with each pixel's reference level in
one fused pass (`_render_events_kernel`, nogil, so two sensors run in parallel). A pixel crossing k
thresholds in one sub-step emits k events at times linearly interpolated between the two
renders. This is the noise-free case of `firmware_sim.event_model`, whose kernel works on
whole frames with per-pixel state (mismatch, noise, refractory, low-pass); the two stay
separate because fusing rendering into the comparison is what makes this one real-time.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from firmware_sim.keyed_step import sort_by_time
from firmware_sim.scene import LOG_LUT_SCALE, Scene, View, lin_log, log_lut
from firmware_sim.world import DeviceClock
from rigd.core.events import EventArray

#: Largest sprite motion between two renders, in pixels.
MAX_STEP_PX = 3.0
#: Longest true time between two renders, us, however slowly the sprites move: the event
#: times are interpolated linearly between renders, and the e2calib reconstruction of the
#: board scene measurably loses focal accuracy with 10 ms steps (docs/simulation.md).
MAX_STEP_US = 5_000.0

I64 = NDArray[np.int64]
F32 = NDArray[np.float32]
#: Output columns the kernels write events into: x, y, polarity, device time.
Out = tuple[NDArray[np.uint16], NDArray[np.uint16], NDArray[np.int8], I64]
#: A device clock as the kernels take it: (offset_us, rate); stamp = floor(offset + t * rate).
Clock = tuple[float, float]


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
    clock: Clock,
    out: Out,
    n: int,
) -> tuple[int, float]:
    """Events of one pixel whose log level went lp -> ln in [t0, t0 + dt] with reference r.

    Returns (new n, new reference), or (-1, r) when the output has no room for them.
    Each crossing of r + m * threshold is timed by linear interpolation between lp and ln
    and stamped like DeviceClock.stamp: floor(c_off + t * c_rate).
    """
    c_off, c_rate = clock
    out_x, out_y, out_p, out_t = out
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


# A numba kernel takes every array as a parameter of its own: its signature is alike in shape
# to keyed_step's kernels, with nothing to share.
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
    clock: Clock,
    start: int,
    out: Out,
    n_out: int,
) -> tuple[int, int]:
    """Events of one sub-step [t0, t1] from two log images of a box with top-left (x0, y0).

    The reference kernel of the per-pixel rule (`_render_events_kernel` fuses it with
    rendering); tests pin the rule with it.

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
            clock,
            out,
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
    clock: Clock,
    y_start: int,
    y_end: int,
    out: Out,
    n_out: int,
) -> tuple[int, int]:
    """Render the log intensity at t1 where sprites are or were, and emit the events since t0.

    Only pixels inside some sprite's quad at t0 or t1 (`quads`: (n, 2, 4, 2) image corners)
    can change, so each row visits just the union of those spans. Per row: each sprite in
    turn is inverse-mapped along its own span (bilinear, alpha compositing over the
    background, float32), then every pixel of the spans goes through the log table and is
    compared with its reference. `last_log` (the log image at t0) and `ref` are full-frame
    and updated in place; uncovered pixels read the view's precomputed background log. Rows
    are atomic: when a row might not fit in the outputs, returns (n_out, that row) for the
    caller to grow them and resume.
    """
    _height, width = bg_int.shape
    cap = out[0].shape[0]
    n_spr = texels.shape[0]
    dt = t1 - t0
    lut_max = lut.shape[0] - 2.0
    side = stack.shape[1]
    row = side * 2
    flat = stack.reshape(-1)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    lo = np.empty(n_spr, np.int64)
    hi = np.empty(n_spr, np.int64)
    seg_lo = np.empty(n_spr, np.int64)
    seg_hi = np.empty(n_spr, np.int64)
    # One row of composited intensity and whether a sprite covers each pixel.
    acc = np.empty(width, np.float32)
    hit = np.zeros(width, np.bool_)
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
        if n_out + row_px * kmax > cap:
            return n_out, y
        for i in range(n_seg):
            for x in range(seg_lo[i], seg_hi[i]):
                acc[x] = bg_int[y, x]
                hit[x] = False
        # Composite sprite by sprite over the row (in sprite order), each along its own span:
        # straight loops in float32, twice as fast as visiting every sprite at every pixel.
        for s in range(n_spr):
            # The inverse homography on this row: (u, v, w) numerators are linear in x.
            h00 = np.float32(hinv[s, 0, 0])
            h01 = np.float32(hinv[s, 0, 1] * fy + hinv[s, 0, 2])
            h10 = np.float32(hinv[s, 1, 0])
            h11 = np.float32(hinv[s, 1, 1] * fy + hinv[s, 1, 2])
            h20 = np.float32(hinv[s, 2, 0])
            h21 = np.float32(hinv[s, 2, 1] * fy + hinv[s, 2, 2])
            lim = np.float32(texels[s] - 1)
            for x in range(lo[s], hi[s]):
                fx = np.float32(x)
                rw = one / (h20 * fx + h21)
                u = (h00 * fx + h01) * rw
                v = (h10 * fx + h11) * rw
                if u < zero or v < zero or u >= lim or v >= lim:
                    continue
                iu = int(u)
                iv = int(v)
                fu = u - np.float32(iu)
                fv = v - np.float32(iv)
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
                acc[x] = acc[x] * (one - al) + pa
                hit[x] = True
        for i in range(n_seg):
            for x in range(seg_lo[i], seg_hi[i]):
                if hit[x]:
                    f = min(max(acc[x], zero) * lut_scale, lut_max)
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
                    clock,
                    out,
                    n_out,
                )
                ref[y, x] = r
                last_log[y, x] = ln
    return n_out, y_end


class EventBuffer:
    """Growable struct-of-arrays the kernels write into (times already device stamps)."""

    def __init__(self, capacity: int = 1 << 15) -> None:
        self.x = np.empty(capacity, np.uint16)
        self.y = np.empty(capacity, np.uint16)
        self.p = np.empty(capacity, np.int8)
        self.t = np.empty(capacity, np.int64)
        self.n = 0

    @property
    def columns(self) -> Out:
        """The output columns as the kernels take them (valid until the next `grow`)."""
        return self.x, self.y, self.p, self.t

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
        t = self.t[:n]
        return sort_by_time(self.x[:n], self.y[:n], self.p[:n], t, int(t.min()), int(t.max()))


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
    stamp: Clock = (clock.offset_us, clock.rate) if clock is not None else (0.0, 1.0)
    times, hs = scene.step_homographies(view, t0_us, t1_us, MAX_STEP_PX, MAX_STEP_US)
    n_sub = len(times) - 1
    corners = scene.corners_of(hs)  # (n_sub + 1, n_obj, 4, 2)
    hinvs = np.linalg.inv(hs[1:])
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
                stamp,
                y,
                y_hi,
                out.columns,
                out.n,
            )
            if y >= y_hi:
                break
            out.grow()
    return out


_LUT = log_lut()


#: Slices `warm_up_generator` tries at most until the fused kernel has run (objects in view).
_WARM_SLICES = 200


def warm_up_generator(
    scene: Scene, view: View, threshold: float, clock: DeviceClock, t_us: float
) -> EventArray:
    """Compile (or load from numba's cache) the kernels `generate_events` and `to_array` run,
    on throwaway copies of the log image and reference from `t_us` on: slices of `step_us`
    until the fused kernel has run once (an object was in view), at most `_WARM_SLICES`.
    Returns the events of the last slice (for warming an encoder on the same types)."""
    step_us = 5_000.0
    last_log = lin_log(scene.render_intensity(view, t_us))
    ref = last_log.copy()
    events = EventArray.empty()
    t = t_us
    for _ in range(_WARM_SLICES):
        buf = generate_events(scene, view, last_log, ref, threshold, t, t + step_us, clock)
        t += step_us
        if buf.n:
            events = buf.to_array()
        if _render_events_kernel.signatures or not scene.objects:
            break
    one = np.zeros(1, np.uint16)
    sort_by_time(one, one.copy(), np.ones(1, np.int8), np.zeros(1, np.int64), 0, 0)  # the counting sort
    return events
