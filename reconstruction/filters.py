"""Background-activity filter (BAF): drop events without spatio-temporal support.

The 4D E-SloMo paper denoises the event streams before everything else: an event is kept only if
at least `min_support` (2) *neighbouring pixels* fired an event of the *same polarity* within a
spatial radius of `radius_px` (3) and within `window_us` (30 us) *before* it. Isolated events
(shot noise, leak) have no such support; edges of moving objects do, because an edge crosses
adjacent pixels within microseconds.

Definitions (the brute-force reference in the tests follows them literally):

* neighbourhood: pixels (x + dx, y + dy) with (dx, dy) != (0, 0) and, by default,
  max(|dx|, |dy|) <= radius (Chebyshev: a 7 x 7 square for r = 3, the window every hardware BAF
  uses); `metric="euclidean"` uses dx^2 + dy^2 <= r^2 (a disc, 28 neighbours for r = 3). The
  event's own pixel is not a neighbour: a hot pixel must not support itself.
* support: a neighbour pixel counts once if some *strictly previous* event (earlier in the
  stream order; equal timestamps count when earlier in the array) of the same polarity at that
  pixel has t_event - t_prev <= window_us.
* state: every event, kept or dropped, updates its pixel's last timestamp (as the classic BAF
  and dv-processing do: support is evidence of activity, not of signal). `update_on_drop=False`
  makes only kept events update the state.

Because the input is time-sorted, "some previous event within the window" is the same as "the
latest previous event at that pixel is within the window", so the state is one time per pixel
and polarity, and the filter streams over chunks: filtering chunk by chunk gives exactly the
result of filtering the concatenation.

Speed (the cost is the map's memory traffic, not arithmetic): the times are int16 relative to a
base that moves forward every ~33 ms of stream (int32 for windows over 32767 us), and the map
interleaves 4 rows per group, so one masked 64-byte vector compare covers 8 columns x 4 rows and
the 7 x 7 neighbourhood takes 2-3 of them (docs/reconstruction.md, "BAF definition").
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from numba import njit
from numpy.typing import NDArray

from rigd.core.events import EventArray

log = logging.getLogger(__name__)

Metric = Literal["chebyshev", "euclidean"]


def neighbour_offsets(
    radius: int, metric: Metric = "chebyshev"
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(dx, dy) of the neighbourhood, own pixel excluded, row by row (dy outer) for cache locality."""
    if radius < 1:
        raise ValueError(f"radius must be >= 1 px, got {radius}")
    if metric not in ("chebyshev", "euclidean"):
        raise ValueError(f"metric must be 'chebyshev' or 'euclidean', got {metric!r}")
    r = np.arange(-radius, radius + 1)
    dy, dx = (a.ravel() for a in np.meshgrid(r, r, indexing="ij"))
    keep = (dx != 0) | (dy != 0)
    if metric == "euclidean":
        keep &= dx * dx + dy * dy <= radius * radius
    return dx[keep].astype(np.int64), dy[keep].astype(np.int64)


def row_half_widths(radius: int, metric: Metric = "chebyshev") -> NDArray[np.int64]:
    """Half width of the neighbourhood in each row dy = -r..r (the kernel scans rows, not offsets)."""
    dx, dy = neighbour_offsets(radius, metric)
    return np.array([int(np.abs(dx[dy == d]).max()) for d in range(-radius, radius + 1)], np.int64)


#: Rows of the map interleaved per group: the map is (polarity, row // 4, column, row % 4), so one
#: 64-byte vector holds 8 columns x 4 rows and the 7 x 7 neighbourhood is 2-3 vector compares
#: (the kernel's source writes the 4 as shifts and masks).
ROWS_PER_GROUP = 4
#: Columns one vector compare covers (32 lanes = 8 columns x 4 rows).
COLS_PER_VECTOR = 8
_LANES = ROWS_PER_GROUP * COLS_PER_VECTOR
#: Longest window kept in int16 times (half the map, so a 640x480 map fits a 2 MB L2); longer
#: windows use int32 times.
INT16_MAX_WINDOW_US = int(np.iinfo(np.int16).max)
#: Longest supported window.
MAX_WINDOW_US = 1 << 29


def map_dtype(window_us: int) -> type[np.signedinteger[Any]]:
    """Storage type of the time map: int16 for windows up to ~33 ms, int32 beyond."""
    return np.int16 if window_us <= INT16_MAX_WINDOW_US else np.int32


@njit(nogil=True, cache=True)
def _validate(  # pragma: no cover - numba
    x: NDArray[np.uint16], y: NDArray[np.uint16], t: NDArray[np.int64], width: int, height: int, t_prev: int
) -> int:
    """0 when the chunk is usable, 1 unsorted (or before t_prev), 2 coordinates off the sensor.

    Integer or- and max-reductions without early exit, so LLVM vectorizes both passes (a bool
    `|=` reduction did not vectorize and took twice as long)."""
    n = t.shape[0]
    if n == 0:
        return 0
    unsorted = np.int64(t_prev > t[0])
    for i in range(1, n):
        unsorted |= np.int64(t[i - 1] > t[i])
    if unsorted:
        return 1
    mx = np.uint16(0)
    my = np.uint16(0)
    for i in range(n):
        mx = max(mx, x[i])
        my = max(my, y[i])
    return 2 if (mx >= width or my >= height) else 0


@njit(nogil=True, cache=True)
def _rebase(flat: NDArray[Any], shift: int, never: int) -> None:  # pragma: no cover - numba
    """Move the time origin `shift` us forward: every stored time minus shift, saturating at `never`."""
    for k in range(flat.shape[0]):
        v = np.int64(flat[k]) - shift
        flat[k] = never if v < never else v


@njit(nogil=True, cache=True)
def _prepare(  # pragma: no cover - numba
    x: NDArray[np.uint16],
    y: NDArray[np.uint16],
    p: NDArray[np.int8],
    s: NDArray[np.int64],
    plane: int,
    cols: int,
) -> None:
    """Per event of a block: the map index of its neighbourhood's first vector, or'ed with its row
    phase (the index is a multiple of 4). A vectorized pass over a cache-sized block, so the serial
    scan loads one int64 per event (and one for the event it prefetches) instead of x, y and p."""
    for i in range(x.shape[0]):
        yi = np.int64(y[i])
        s[i] = (np.int64(p[i] > 0) * plane + ((yi >> 2) * cols + np.int64(x[i])) * 4) | (yi & 3)


def _count_ge(typingctx: Any, arr: Any, start: Any, lim: Any, bits: Any) -> Any:
    """popcount(bits & (flat[start:start + 32] >= lim)) as one masked <32 x int> load (lanes outside
    `bits` are not read and read as "never"), one vector compare and one popcount: no gathers, no
    branches (LLVM's vectorizers do not find this in the unrolled neighbourhood scan)."""
    from llvmlite import ir as llir
    from numba import types as nbt

    if not (isinstance(arr, nbt.Array) and arr.dtype in (nbt.int16, nbt.int32) and arr.ndim == 1):
        return None
    sig = nbt.int64(arr, start, lim, bits)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        a, st, lm, mb = args
        elem = signature.args[0].dtype
        ary = context.make_array(signature.args[0])(context, builder, a)
        st = context.cast(builder, st, signature.args[1], nbt.int64)
        lm = context.cast(builder, lm, signature.args[2], elem)
        mb = context.cast(builder, mb, signature.args[3], nbt.int64)
        ety = context.get_value_type(elem)
        vty = llir.VectorType(ety, _LANES)
        mty = llir.VectorType(llir.IntType(1), _LANES)
        i32 = llir.IntType(32)
        pty = vty.as_pointer()
        suffix = "p0" if getattr(pty, "is_opaque", False) else f"p0v{_LANES}i{ety.width}"
        name = f"llvm.masked.load.v{_LANES}i{ety.width}.{suffix}"
        fn = builder.module.globals.get(name) or llir.Function(
            builder.module, llir.FunctionType(vty, [pty, i32, mty, vty]), name
        )
        lane_mask = builder.bitcast(builder.trunc(mb, llir.IntType(_LANES)), mty)
        never = llir.Constant(vty, [int(np.iinfo(np.dtype(str(elem))).min)] * _LANES)
        ptr = builder.bitcast(builder.gep(ary.data, [st]), pty)
        vec = builder.call(fn, [ptr, llir.Constant(i32, ety.width // 8), lane_mask, never])
        undef = llir.Constant(vty, llir.Undefined)
        splat = builder.insert_element(undef, lm, llir.Constant(i32, 0))
        splat = builder.shuffle_vector(
            splat, undef, llir.Constant(llir.VectorType(i32, _LANES), [0] * _LANES)
        )
        hit = builder.bitcast(builder.icmp_signed(">=", vec, splat), llir.IntType(_LANES))
        return builder.zext(builder.ctpop(hit), llir.IntType(64))

    return sig, codegen


@functools.lru_cache(maxsize=1)
def _count_ge_intrinsic() -> Callable[..., int]:
    from numba.extending import intrinsic

    return intrinsic(_count_ge)


def _prefetch(typingctx: Any, arr: Any, start: Any) -> Any:
    """Prefetch the cache line of flat[start] (llvm.prefetch: read, keep in all levels)."""
    from llvmlite import ir as llir
    from numba import types as nbt

    if not (isinstance(arr, nbt.Array) and arr.ndim == 1):
        return None
    sig = nbt.void(arr, start)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        a, st = args
        ary = context.make_array(signature.args[0])(context, builder, a)
        st = context.cast(builder, st, signature.args[1], nbt.int64)
        i8p = llir.IntType(8).as_pointer()
        i32 = llir.IntType(32)
        name = "llvm.prefetch.p0" if getattr(i8p, "is_opaque", False) else "llvm.prefetch.p0i8"
        fn = builder.module.globals.get(name) or llir.Function(
            builder.module, llir.FunctionType(llir.VoidType(), [i8p, i32, i32, i32]), name
        )
        ptr = builder.bitcast(builder.gep(ary.data, [st]), i8p)
        builder.call(fn, [ptr, llir.Constant(i32, 0), llir.Constant(i32, 3), llir.Constant(i32, 1)])
        return context.get_dummy_value()

    return sig, codegen


@functools.lru_cache(maxsize=1)
def _prefetch_intrinsic() -> Callable[..., None]:
    from numba.extending import intrinsic

    return intrinsic(_prefetch)


#: Events per block of the kernel (its index work space: 32 KiB, so it stays in L1/L2).
BLOCK_EVENTS = 4096
#: Events ahead whose neighbourhood lines the kernel prefetches: on a map larger than L2 (a
#: 1280x720 sensor) the lines of scattered events otherwise arrive one miss at a time.
PREFETCH_AHEAD = 32


class MapLayout:
    """Geometry of the padded, row-interleaved time map for one sensor and neighbourhood.

    Row y of the sensor is padded row y + r, stored in group (y + r) // 4 at lane (y + r) % 4; column
    x is padded column x + r. The neighbourhood's rows y - r .. y + r start in group y // 4 at lane
    y % 4 (the "phase"), span at most `groups` groups, and its columns x - r .. x + r are read as
    `segments` vectors of 8 columns from column x; padding (never fired) makes every read in bounds."""

    def __init__(self, width: int, height: int, radius: int, half: tuple[int, ...]) -> None:
        diam = 2 * radius + 1
        self.radius = radius
        self.groups = -(-(diam + ROWS_PER_GROUP - 1) // ROWS_PER_GROUP)
        self.segments = -(-diam // COLS_PER_VECTOR)
        self.cols = width + self.segments * COLS_PER_VECTOR - 1
        self.n_groups = (height - 1) // ROWS_PER_GROUP + self.groups
        self.plane = self.n_groups * self.cols * ROWS_PER_GROUP
        # lane masks per phase, group and segment: in the neighbourhood's shape, own pixel excluded
        masks = np.zeros((ROWS_PER_GROUP, self.groups, self.segments), np.uint32)
        for phase in range(ROWS_PER_GROUP):
            for g in range(self.groups):
                for s in range(self.segments):
                    bits = 0
                    for lane in range(_LANES):
                        row = g * ROWS_PER_GROUP + lane % ROWS_PER_GROUP - phase  # 0 .. 2r
                        dx = s * COLS_PER_VECTOR + lane // ROWS_PER_GROUP - radius
                        if 0 <= row < diam and abs(dx) <= half[row] and not (row == radius and dx == 0):
                            bits |= 1 << lane
                    masks[phase, g, s] = bits
        self.masks = masks
        # own pixel's index minus the first vector's, per phase
        self.own_offset = np.array(
            [((ph + radius) >> 2) * self.cols * 4 + radius * 4 + ((ph + radius) & 3) for ph in range(4)],
            np.int64,
        )


@functools.lru_cache(maxsize=32)
def _make_kernel(
    radius: int, groups: int, segments: int, update_on_drop: bool, dtype: str
) -> Callable[..., int]:
    """Kernel specialised to one neighbourhood size and update rule, generated as source: the scan is
    groups x segments masked vector compares summed branch-free; no per-event branch on options.
    `dtype` is the map's (int16 or int32); the kernel returns the time base, which it moves forward
    (a rebase of the map, saturating old times to "never") when a time leaves the map's range."""
    info = np.iinfo(dtype)
    terms = [
        f"cnt(flat, start + {g * ROWS_PER_GROUP} * cols + {s * _LANES}, lim, masks[phase, {g}, {s}])"
        for g in range(groups)
        for s in range(segments)
    ]
    store = "flat[own] = ti" if update_on_drop else "if ok:\n            flat[own] = ti"
    # every cache line of the vectors the event PREFETCH_AHEAD later will read
    step = 64 // np.dtype(dtype).itemsize
    offsets = sorted({*range(0, _LANES, step), _LANES - 1})
    prefetches = "\n        ".join(
        f"prefetch(flat, ahead + {g * ROWS_PER_GROUP} * cols + {s * _LANES + o})"
        for g in range(groups)
        for s in range(segments)
        for o in offsets
    )
    src = f"""
def scan(s, t, base, flat, masks, own_off, cols, window_us, min_support, keep):
    n = t.shape[0]
    for i in range(n):
        ahead = s[min(i + {PREFETCH_AHEAD}, n - 1)] & -4
        {prefetches}
        rel = t[i] - base
        if rel > {info.max}:
            rebase(flat, min(rel, {2 * info.max + 2}), {info.min})
            base = t[i]
            rel = 0
        ti = np.{dtype}(rel)
        lim = np.{dtype}(rel - window_us)
        phase = s[i] & 3
        start = s[i] & -4
        ok = ({" + ".join(terms)}) >= min_support
        keep[i] = ok
        own = np.uint64(start + own_off[phase])
        {store}
    return base


def kernel(x, y, p, t, base_us, flat, masks, own_off, cols, plane, window_us, min_support, keep, s):
    base = base_us
    n = t.shape[0]
    for a in range(0, n, s.shape[0]):
        e = min(n, a + s.shape[0])
        prepare(x[a:e], y[a:e], p[a:e], s, plane, cols)
        base = scan(s[: e - a], t[a:e], base, flat, masks, own_off, cols, window_us, min_support, keep[a:e])
    return base
"""
    env: dict[str, Any] = {
        "np": np,
        "cnt": _count_ge_intrinsic(),
        "prefetch": _prefetch_intrinsic(),
        "rebase": _rebase,
        "prepare": _prepare,
    }
    exec(compile(src, f"<BAF kernel r={radius} update_on_drop={update_on_drop} {dtype}>", "exec"), env)
    env["scan"] = njit(nogil=True, boundscheck=False)(env["scan"])
    kernel: Callable[..., int] = njit(nogil=True, boundscheck=False)(env["kernel"])
    return kernel


class BackgroundActivityFilter:
    """Streaming BAF over time-sorted chunks of one sensor (state: last timestamp per pixel/polarity).

    `filter(events)` returns the kept events; `mask(events)` the boolean keep mask. Chunks must
    be given in time order (each chunk sorted, and not earlier than the previous chunk's end);
    the result is then independent of how the stream is cut. `reset()` forgets the past.
    """

    def __init__(
        self,
        width: int,
        height: int,
        *,
        radius_px: int = 3,
        window_us: int = 30,
        min_support: int = 2,
        metric: Metric = "chebyshev",
        update_on_drop: bool = True,
    ) -> None:
        if not (0 < width <= 65536 and 0 < height <= 65536):
            raise ValueError(f"geometry {width}x{height} out of range (1..65536)")
        if not 0 <= window_us <= MAX_WINDOW_US:
            raise ValueError(f"window_us must be in 0..{MAX_WINDOW_US}, got {window_us}")
        if min_support < 0:
            raise ValueError(f"min_support must be >= 0, got {min_support}")
        self.width, self.height = int(width), int(height)
        self.radius_px = int(radius_px)
        self.window_us = int(window_us)
        self.min_support = int(min_support)
        self.metric: Metric = metric
        self.update_on_drop = bool(update_on_drop)
        r = self.radius_px
        half = tuple(int(h) for h in row_half_widths(r, metric))
        self._layout = MapLayout(self.width, self.height, r, half)
        self._dtype = map_dtype(self.window_us)
        self._never = int(np.iinfo(self._dtype).min)
        self._kernel = _make_kernel(
            r, self._layout.groups, self._layout.segments, self.update_on_drop, np.dtype(self._dtype).name
        )
        self._last = np.full(2 * self._layout.plane, self._never, self._dtype)
        self._index = np.empty(BLOCK_EVENTS, np.int64)  # the scan's per-block work space
        self._base_us: int | None = None
        self._t_end: int | None = None
        self.n_in = 0
        self.n_kept = 0

    def reset(self) -> None:
        """Forget every pixel's history (e.g. at a discontinuity in the stream)."""
        self._last.fill(self._never)
        self._t_end = None
        self._base_us = None

    def mask(self, events: EventArray) -> NDArray[np.bool_]:
        """Keep mask of one chunk, advancing the state."""
        n = len(events)
        keep = np.zeros(n, np.bool_)
        if n == 0:
            return keep
        t = events.t
        t_prev = np.iinfo(np.int64).min if self._t_end is None else self._t_end
        code = _validate(events.x, events.y, t, self.width, self.height, t_prev)
        if code == 1:
            raise ValueError(
                "BackgroundActivityFilter: events must be sorted by time, and a chunk must not start before "
                f"the previous chunk's end ({self._t_end} us); give chunks in time order or call reset()"
            )
        if code == 2:
            raise ValueError(
                f"BackgroundActivityFilter: event coordinates outside the {self.width}x{self.height} sensor"
            )
        if self._base_us is None:
            self._base_us = int(t[0])
        lay = self._layout
        self._base_us = int(
            self._kernel(
                events.x,
                events.y,
                events.p,
                t,
                self._base_us,
                self._last,
                lay.masks,
                lay.own_offset,
                lay.cols,
                lay.plane,
                self.window_us,
                self.min_support,
                keep,
                self._index,
            )
        )
        self._t_end = int(t[-1])
        kept = int(np.count_nonzero(keep))
        self.n_in += n
        self.n_kept += kept
        log.debug("BAF: kept %d of %d events", kept, n)
        return keep

    def filter(self, events: EventArray) -> EventArray:
        """The kept events of one chunk, advancing the state."""
        return events[self.mask(events)]


def background_activity_filter(
    events: EventArray,
    width: int,
    height: int,
    *,
    radius_px: int = 3,
    window_us: int = 30,
    min_support: int = 2,
    metric: Metric = "chebyshev",
    update_on_drop: bool = True,
) -> EventArray:
    """One-shot BAF of a whole (time-sorted) event array with the paper's defaults."""
    baf = BackgroundActivityFilter(
        width,
        height,
        radius_px=radius_px,
        window_us=window_us,
        min_support=min_support,
        metric=metric,
        update_on_drop=update_on_drop,
    )
    return baf.filter(events)
