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
base that moves forward every ~65 ms of stream (int32 for windows over 32767 us), and the map
interleaves 4 rows per group, so one 64-byte vector compare covers 8 columns x 4 rows and the
7 x 7 neighbourhood takes 3 of them (docs/reconstruction.md, "BAF definition"). The input is
checked block by block inside the kernel, so the events are read from memory once, and `filter()`
copies each block's kept events out while the block is in cache instead of indexing every array
with the mask. `threads=2` filters the two polarities on two threads, each against its own half
of the map (docs/benchmarks.md, "Background-activity filter"). The compiled parts are in
`reconstruction.baf_kernels`.
"""

from __future__ import annotations

import logging
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from reconstruction.baf_kernels import (
    BAD_PLACE,
    GOOD,
    MAX_WINDOW_US,
    PREFETCH_AHEAD,
    MapLayout,
    first_bad,
    gather_merged,
    halves,
    make_kernel,
    map_dtype,
    on_two_threads,
    scatter,
)
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


#: Bytes per event a separate validation pass reads (t, x, y): a chunk that reads more than twice
#: the map is checked inside the kernel instead, against a copy of the map to restore on failure.
CHECK_BYTES_PER_EVENT = 12
#: Events per block of the kernel (its index work space: 32 KiB, so it stays in L1/L2; threads=2
#: lists a block's positions as int16, so at most 32767 with the prefetched events).
BLOCK_EVENTS = 4096
#: Smallest chunk `threads=2` splits by polarity: below it, starting the second thread costs more
#: than half the chunk's scan.
SPLIT_MIN_EVENTS = 1 << 16
#: Largest share of one polarity `threads=2` splits (estimated from every 64th event): the slower
#: thread's half sets the time, and above ~60 % the split no longer pays for the merge (the real
#: Gen3 recording, 68 % ON, was slower on two threads than on one).
SPLIT_MAX_SHARE = 0.6
#: Largest chunk `filter()` runs in one kernel call: it writes the kept events into arrays sized for
#: the whole chunk (only the pages it fills are touched) and returns views of them, so a larger
#: input is filtered in slices of this many events, which bounds the address space reserved.
FILTER_SLICE_EVENTS = 1 << 24


class BackgroundActivityFilter:
    """Streaming BAF over time-sorted chunks of one sensor (state: last timestamp per pixel/polarity).

    `filter(events)` returns the kept events; `mask(events)` the boolean keep mask. Chunks must
    be given in time order (each chunk sorted, and not earlier than the previous chunk's end);
    the result is then independent of how the stream is cut. `reset()` forgets the past.

    `threads=2` filters the ON and the OFF events of a chunk on two threads: the rule never
    mixes polarities, so each thread owns one plane of the map and the result is identical.
    Leave it at 1 where chunks already run in parallel (the reconstruct pipeline's workers).
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
        threads: int = 1,
    ) -> None:
        if threads not in (1, 2):
            raise ValueError(f"threads must be 1 or 2 (one per polarity), got {threads}")
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
        self.threads = int(threads)
        r = self.radius_px
        half = tuple(int(h) for h in row_half_widths(r, metric))
        self._layout = MapLayout(self.width, self.height, r, half)
        self._dtype = map_dtype(self.window_us)
        self._never = int(np.iinfo(self._dtype).min)
        lay = self._layout
        kind = (r, lay.groups, lay.segments, self.update_on_drop, np.dtype(self._dtype).name)
        self._kernels = {gather: make_kernel(*kind, gather) for gather in (False, True)}
        self._split_kernel = make_kernel(*kind, True, True) if self.threads == 2 else None
        self._last = np.full(2 * self._layout.plane, self._never, self._dtype)
        # per thread: the block's map indices (with the events it prefetches past the block's end); one
        # thread's list of a block's kept events (filter()); with threads=2 each thread's events of its
        # polarity
        words = BLOCK_EVENTS + PREFETCH_AHEAD
        self._index = [np.empty(words, np.int64) for _ in range(self.threads)]
        self._listed = np.empty(words, np.int64)
        self._packs = [(np.empty(words, np.uint8), np.empty(words, np.int16)) for _ in range(self.threads)]
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
        keep = np.zeros(len(events), np.bool_)
        if self._splits(events):
            off, on = self._run_split(events)
            i, j = halves(off, on, len(events))

            def low() -> None:
                scatter(keep, off[:i])
                scatter(keep, on[:j])

            def high() -> None:
                scatter(keep, off[i:-1])
                scatter(keep, on[j:-1])

            on_two_threads(low, high, "baf-mask")
        elif len(events):
            self._run(events, keep, None)
        return keep

    def filter(self, events: EventArray) -> EventArray:
        """The kept events of one chunk, advancing the state. The kernel copies each block's kept
        events out while the block is in cache: no mask, and no second read of the chunk."""
        n = len(events)
        if n > FILTER_SLICE_EVENTS:
            return EventArray.concatenate(
                [self.filter(events[a : a + FILTER_SLICE_EVENTS]) for a in range(0, n, FILTER_SLICE_EVENTS)]
            )
        if n == 0:
            return EventArray.empty()
        if not self._splits(events):
            out = _empty_like(events, n)
            kept = self._run(events, None, out)
            return out[:kept]
        off, on = self._run_split(events)
        out = _empty_like(events, len(off) + len(on) - 2)
        i, j = halves(off, on, n)
        x, y, p, t = events.x, events.y, events.p, events.t
        # the first half's merge stops at its output's end, on heads >= the middle (its sentinels)
        first, second = out[: i + j], out[i + j :]
        on_two_threads(
            lambda: gather_merged(x, y, p, t, off, on, first.x, first.y, first.p, first.t),
            lambda: gather_merged(x, y, p, t, off[i:], on[j:], second.x, second.y, second.p, second.t),
            "baf-gather",
        )
        return out

    def _splits(self, events: EventArray) -> bool:
        """Whether this chunk runs as two polarity threads: large enough (int32 indices: under
        2**31 events) and with neither polarity much more than half of it."""
        if not (self.threads == 2 and max(1, SPLIT_MIN_EVENTS) <= len(events) < 2**31 - 1):
            return False
        on = float(np.mean(events.p[::64] > 0))
        return max(on, 1.0 - on) <= SPLIT_MAX_SHARE

    def _check(self, events: EventArray, t_prev: int) -> NDArray[Any] | None:
        """Validate a small chunk now (raising); for a large one, the map's copy to restore if the
        kernel finds it bad (the kernel validates it block by block as it goes)."""
        if len(events) * CHECK_BYTES_PER_EVENT > 2 * self._last.nbytes:
            return self._last.copy()
        x, y, t = events.x, events.y, events.t
        self._raise_if_bad(events, first_bad(x, y, t, self.width, self.height, t_prev))
        return None

    def _fail(self, events: EventArray, bad: int, snapshot: NDArray[Any] | None) -> None:
        """Put the map back and raise for the bad event the kernel found."""
        if snapshot is None:  # checked before the kernel: the kernel disagrees with first_bad
            raise AssertionError(f"BAF kernel found bad event {bad // 2} in a chunk that was checked")
        np.copyto(self._last, snapshot)
        self._raise_if_bad(events, int(bad))

    def _start(self, events: EventArray) -> tuple[int, int]:
        """(previous chunk's last time, or the lowest int64; the map's time base for this chunk)."""
        t_prev = np.iinfo(np.int64).min if self._t_end is None else self._t_end
        low = int(np.iinfo(self._dtype).min) + 1 + self.window_us
        return int(t_prev), int(events.t[0]) - low if self._base_us is None else self._base_us

    def _advance(self, events: EventArray, base: int, kept: int) -> None:
        self._base_us = int(base)
        self._t_end = int(events.t[-1])
        self.n_in += len(events)
        self.n_kept += kept
        log.debug("BAF: kept %d of %d events", kept, len(events))

    def _args(self, events: EventArray, t_prev: int, base: int) -> tuple[Any, ...]:
        """The kernels' leading arguments: the chunk, where the stream stands, the map and the rule."""
        lay = self._layout
        x, y, p, t = events.x, events.y, events.p, events.t
        return (x, y, p, t, t_prev, base, self._last, lay.table, lay.cols, lay.plane, self.width, self.height)

    def _run(self, events: EventArray, keep: NDArray[np.bool_] | None, out: EventArray | None) -> int:
        """Filter one non-empty chunk into the keep mask or, without one, the kept events into `out`;
        the number kept.

        Bad input raises before any state changes: a chunk small next to the map is checked in a
        pass of its own; a larger one is checked block by block inside the kernel (the events are
        then read from memory once) and the map is put back from a copy if a block is bad."""
        t_prev, base = self._start(events)
        snapshot = self._check(events, t_prev)
        if keep is None:
            assert out is not None
        else:
            out = EventArray.empty()  # unused by the mask kernel
        dest: NDArray[Any] = self._listed if keep is None else keep
        base, kept, bad = self._kernels[keep is None](
            *self._args(events, t_prev, base),
            self.window_us,
            self.min_support,
            dest,
            self._index[0],
            out.x,
            out.y,
            out.p,
            out.t,
        )
        if bad != GOOD:
            self._fail(events, int(bad), snapshot)
        kept = int(kept) if keep is None else int(np.count_nonzero(keep))
        self._advance(events, int(base), kept)
        return kept

    def _run_split(self, events: EventArray) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
        """Filter one chunk as two polarity threads: per polarity (OFF, ON), its kept events'
        indices, ascending, ending with a sentinel (len(events)) that `gather_merged` stops on."""
        n = len(events)
        t_prev, base = self._start(events)
        snapshot = self._check(events, t_prev)
        kernel = self._split_kernel
        assert kernel is not None
        lead = self._args(events, t_prev, base)
        # int32 indices (chunks stay under FILTER_SLICE_EVENTS or a mask's length); pages past the kept
        # count are never touched
        lists = [np.empty(n + 1, np.int32) for _ in range(2)]
        results: list[tuple[int, int, int]] = [(0, 0, GOOD)] * 2

        def run(pol: int) -> None:
            on, ic = self._packs[pol]
            s = self._index[pol]
            results[pol] = kernel(*lead, self.window_us, self.min_support, lists[pol], s, pol, on, ic)

        on_two_threads(lambda: run(0), lambda: run(1), "baf-on")
        (base_off, k_off, bad_off), (base_on, k_on, bad_on) = results
        if bad_off != GOOD or bad_on != GOOD:  # both stop at the same block
            self._fail(events, min(b for b in (bad_off, bad_on) if b != GOOD), snapshot)
        if base_off != base_on:
            raise AssertionError(f"BAF polarity threads disagree on the time base ({base_off} != {base_on})")
        off, on = lists[0][: k_off + 1], lists[1][: k_on + 1]
        off[k_off] = on[k_on] = n
        self._advance(events, base_off, k_off + k_on)
        return off, on

    def _raise_if_bad(self, events: EventArray, bad: int) -> None:
        """ValueError naming the first event that is out of order or off the sensor (GOOD: none)."""
        if bad == GOOD:
            return
        i, kind = divmod(bad, 2)
        if kind == BAD_PLACE:
            raise ValueError(
                f"BackgroundActivityFilter: event {i} at (x={int(events.x[i])}, y={int(events.y[i])}) is "
                f"outside the {self.width}x{self.height} sensor"
            )
        if i == 0:
            raise ValueError(
                f"BackgroundActivityFilter: the chunk's first event ({int(events.t[0])} us) is before the "
                f"previous chunk's end ({self._t_end} us); give chunks in time order or call reset()"
            )
        raise ValueError(
            f"BackgroundActivityFilter: events must be sorted by time: event {i} ({int(events.t[i])} us) "
            f"comes before event {i - 1} ({int(events.t[i - 1])} us)"
        )


def _empty_like(events: EventArray, n: int) -> EventArray:
    """n uninitialised events of `events`' dtypes (numpy's allocation: see `baf_kernels._collect`)."""
    x, y, p, t = events.x, events.y, events.p, events.t
    return EventArray(np.empty(n, x.dtype), np.empty(n, y.dtype), np.empty(n, p.dtype), np.empty(n, t.dtype))


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
    threads: int = 1,
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
        threads=threads,
    )
    return baf.filter(events)
