"""The background-activity filter's compiled parts: the map's layout, the kernels generated for
one neighbourhood and output, the LLVM intrinsics they use, and the numba passes around them
(checks, listing one polarity's events, collecting and merging the kept ones).

`reconstruction.filters.BackgroundActivityFilter` drives them; the rule and the layout are
described there and in docs/reconstruction.md ("BAF definition").
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import NDArray

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


#: What `first_bad` returns for a usable chunk; otherwise 2 * index + kind of the first bad event.
GOOD = -1
BAD_ORDER = 0
BAD_PLACE = 1


@njit(nogil=True, cache=True)
def first_bad(  # pragma: no cover - numba
    x: NDArray[np.uint16], y: NDArray[np.uint16], t: NDArray[np.int64], width: int, height: int, t_prev: int
) -> int:
    """GOOD, or 2 * i + BAD_ORDER / BAD_PLACE for the first event i that goes back in time (before
    t_prev for i = 0) or lies off the sensor.

    Integer or- and max-reductions without early exit first, so LLVM vectorizes the usual case (a
    bool `|=` reduction did not vectorize and took twice as long); the exact event only on failure."""
    n = t.shape[0]
    if n == 0:
        return GOOD
    unsorted = np.int64(t_prev > t[0])
    mx = np.uint16(x[0])
    my = np.uint16(y[0])
    for i in range(1, n):
        unsorted |= np.int64(t[i - 1] > t[i])
        mx = max(mx, x[i])
        my = max(my, y[i])
    if unsorted == 0 and mx < width and my < height:
        return GOOD
    for i in range(n):
        if t[i] < (t_prev if i == 0 else t[i - 1]):
            return 2 * i + BAD_ORDER
        if x[i] >= width or y[i] >= height:
            return 2 * i + BAD_PLACE
    return GOOD


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
    t: NDArray[np.int64],
    s: NDArray[np.int64],
    plane: int,
    cols: int,
    width: int,
    height: int,
    t_prev: int,
) -> int:
    """For each event of a block: s[i] = the map index of its neighbourhood's first vector, or'ed with
    its row phase (the index is a multiple of 4); returns the block's validation (`first_bad`). One
    pass over a cache-sized block, so the serial scan loads one int64 per event (and one for the
    event it prefetches) and the events are read from memory once."""
    n = t.shape[0]
    unsorted = np.int64(t_prev > t[0])
    for i in range(1, n):
        unsorted |= np.int64(t[i - 1] > t[i])
    mx = np.uint16(0)
    my = np.uint16(0)
    for i in range(n):
        mx = max(mx, x[i])
        my = max(my, y[i])
    for i in range(n):
        yi = np.int64(y[i])
        s[i] = (np.int64(p[i] > 0) * plane + ((yi >> 2) * cols + np.int64(x[i])) * 4) | (yi & 3)
    if unsorted == 0 and mx < width and my < height:
        return GOOD
    return first_bad(x, y, t, width, height, t_prev)


#: For each 8-bit pattern of "this polarity" over 8 events: the positions of its set bits, then
#: zeros; and how many there are (`_pack` lists 8 events per step without a branch).
_PACK_LANES = np.array(
    [
        [lane for lane in range(8) if bits >> lane & 1] + [0] * (8 - bin(bits).count("1"))
        for bits in range(256)
    ],
    np.int16,
)
_PACK_COUNT = np.array([bin(bits).count("1") for bits in range(256)], np.int64)
#: Gathers the low bit of each of a word's 8 bytes into its top byte (byte i -> bit 56 + i).
_BYTE_BITS = np.uint64(0x0102040810204080)


@njit(nogil=True, cache=True)
def _pack(  # pragma: no cover - numba
    p: NDArray[np.int8], pol: int, on: NDArray[np.uint8], ic: NDArray[np.int16]
) -> int:
    """ic[:m] = the positions in p (at most 2**15) of the events of polarity `pol` (1: p > 0, 0: p <= 0),
    ascending; returns m. Eight events per step: one vectorized pass writes each event's 0/1 into
    `on`; a multiply gathers 8 of them into a byte, which indexes a table of lane positions that is
    stored whole (the lanes past the count are overwritten by the next step)."""
    n = p.shape[0]
    flip = np.uint8(pol != 1)
    for j in range(n):
        on[j] = np.uint8(p[j] > 0) ^ flip
    words = on[: n - n % 8].view(np.uint64)
    m = np.uint64(0)
    for w in range(words.shape[0]):
        bits = (words[w] * _BYTE_BITS) >> np.uint64(56)
        g = np.int16(8 * w)
        for lane in range(8):
            ic[m + np.uint64(lane)] = g + _PACK_LANES[bits, lane]
        m += np.uint64(_PACK_COUNT[bits])
    for j in range(n - n % 8, n):
        ic[m] = j
        m += np.uint64(on[j])
    return int(m)


def _count_ge(typingctx: Any, arr: Any, start: Any, lim: Any, bits: Any) -> Any:
    """popcount(bits & (flat[start:start + 32] >= lim)) as one <32 x int> load folded into one vector
    compare, an and and one popcount: no gathers, no branches (LLVM's vectorizers do not find this
    in the unrolled neighbourhood scan). Every lane is inside the padded map (MapLayout), so the
    load needs no lane mask; lanes outside the neighbourhood are dropped by `bits` afterwards."""
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
        i32 = llir.IntType(32)
        ptr = builder.bitcast(builder.gep(ary.data, [st]), vty.as_pointer())
        vec = builder.load(ptr, align=ety.width // 8)
        undef = llir.Constant(vty, llir.Undefined)
        splat = builder.insert_element(undef, lm, llir.Constant(i32, 0))
        splat = builder.shuffle_vector(
            splat, undef, llir.Constant(llir.VectorType(i32, _LANES), [0] * _LANES)
        )
        hit = builder.bitcast(builder.icmp_signed(">=", vec, splat), llir.IntType(_LANES))
        hit = builder.and_(hit, builder.trunc(mb, llir.IntType(_LANES)))
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
        #: what the kernel looks up per event, one row per phase: the lane masks, then the own offset
        self.table = np.concatenate([masks.reshape(ROWS_PER_GROUP, -1), self.own_offset[:, None]], axis=1)


@functools.lru_cache(maxsize=32)
def make_kernel(
    radius: int,
    groups: int,
    segments: int,
    update_on_drop: bool,
    dtype: str,
    gather: bool,
    split: bool = False,
) -> Callable[..., tuple[int, int, int]]:
    """Kernel specialised to one neighbourhood size, update rule and output, generated as source: the
    scan is groups x segments vector compares summed branch-free; no per-event branch on options.
    `dtype` is the map's (int16 or int32). The output is the keep mask, or with `gather` the kept
    events themselves: the scan lists a block's kept indices branch-free and the block's kept events
    are copied out while the block is still in cache (a gather after the whole chunk read the
    events from memory a second time). Returns (time base, kept events written, GOOD or the first
    bad event as `first_bad` codes it, absolute).

    Times are stored relative to a base. Between rebases the scan runs without a range check; when
    the next time leaves the map's range, the map is rebased (old times saturate to "never") so that
    this time lands at the lowest value whose window still lies above "never": the full range of
    the type, minus the window, passes between rebases.

    With `split` (gather only) the kernel filters the events of one polarity (its `pol` argument)
    against that polarity's plane of the map: each block is validated and indexed whole, its events
    of that polarity are listed (8 at a time, through a table of the 256 lane patterns), and the
    listed ones are scanned; the kept events' indices are listed (int32), for the merge of the two
    polarities. The rebases fall where the whole stream puts
    them, so two such kernels, one per polarity, leave the map and the base exactly as one kernel
    over both would, and they touch disjoint halves of the map (one thread each)."""
    if split and not gather:
        raise ValueError("a polarity-split kernel gathers the kept events")
    info = np.iinfo(dtype)
    terms = [
        f"cnt(flat, start + {g * ROWS_PER_GROUP} * cols + {s * _LANES}, lim, tab[phase, {g * segments + s}])"
        for g in range(groups)
        for s in range(segments)
    ]
    own = f"np.uint64(start + tab[phase, {groups * segments}])"
    store = f"flat[{own}] = ti" if update_on_drop else f"if ok:\n            flat[{own}] = ti"
    out = "out[np.uint64(k)] = first + i\n        k += np.int64(ok)" if gather else "out[i] = ok"
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
def scan(s, t, base, flat, tab, cols, window_us, min_support, out, k, first):
    for i in range(t.shape[0]):
        ahead = s[i + {PREFETCH_AHEAD}] & -4
        {prefetches}
        rel = t[i] - base
        ti = np.{dtype}(rel)
        lim = np.{dtype}(rel - window_us)
        phase = s[i] & 3
        start = s[i] & -4
        ok = ({" + ".join(terms)}) >= min_support
        {out}
        {store}
    return k


def scan_packed(ic, n, s, t, base, flat, tab, cols, window_us, min_support, out, k, first):
    for i in range(n):
        ahead = s[ic[i + {PREFETCH_AHEAD}]] & -4
        {prefetches}
        j = ic[i]
        rel = t[j] - base
        ti = np.{dtype}(rel)
        lim = np.{dtype}(rel - window_us)
        phase = s[j] & 3
        start = s[j] & -4
        ok = ({" + ".join(terms)}) >= min_support
        out[np.uint64(k)] = first + j
        k += np.int64(ok)
        {store}
    return k


def kernel(x, y, p, t, t_prev, base, flat, tab, cols, plane, width, height, window_us, min_support, out, s,
           ox, oy, op, ot):
    n = t.shape[0]
    blk = s.shape[0] - {PREFETCH_AHEAD}
    low = {info.min + 1} + window_us  # the lowest relative time whose window lies above "never"
    k = 0
    for a in range(0, n, blk):
        e = min(n, a + blk)
        pe = min(n, e + {PREFETCH_AHEAD})
        before = t_prev if a == 0 else t[a - 1]
        bad = prepare(x[a:pe], y[a:pe], p[a:pe], t[a:pe], s, plane, cols, width, height, before)
        if bad != {GOOD}:
            return base, k, bad + 2 * a
        for j in range(pe - a, s.shape[0]):  # the last events prefetch the block's last
            s[j] = s[pe - a - 1]
        kb = 0
        lo = a
        while lo < e:
            top = base + {info.max}
            hi = e if t[e - 1] <= top else lo + np.searchsorted(t[lo:e], top, side="right")
            part = out if {gather} else out[lo:hi]
            kb = scan(s[lo - a :], t[lo:hi], base, flat, tab, cols, window_us, min_support, part, kb, lo)
            if hi < e:
                rebase(flat, min(t[hi] - base - low, {info.max - info.min + 1}), {info.min})
                base = t[hi] - low
            lo = hi
        if {gather}:
            k = collect(x, y, p, t, out, kb, ox, oy, op, ot, k)
    return base, k, {GOOD}


def split_kernel(x, y, p, t, t_prev, base, flat, tab, cols, plane, width, height, window_us, min_support, out,
                 s, pol, on, ic):
    n = t.shape[0]
    blk = s.shape[0] - {PREFETCH_AHEAD}
    low = {info.min + 1} + window_us
    mine = flat[pol * plane : (pol + 1) * plane]
    k = 0
    for a in range(0, n, blk):
        e = min(n, a + blk)
        before = t_prev if a == 0 else t[a - 1]
        bad = prepare(x[a:e], y[a:e], p[a:e], t[a:e], s, plane, cols, width, height, before)
        if bad != {GOOD}:
            return base, k, bad + 2 * a
        m = pack(p[a:e], pol, on, ic)
        pad = ic[m - 1] if m > 0 else 0
        for j in range(m, m + {PREFETCH_AHEAD}):  # the last events prefetch the block's last
            ic[j] = pad
        lo = a
        lc = 0
        while lo < e:
            top = base + {info.max}
            if t[e - 1] <= top:
                hi = e
                hc = m
            else:
                hi = lo + np.searchsorted(t[lo:e], top, side="right")
                hc = lc + np.searchsorted(ic[lc:m], hi - a)
            tb = t[a:e]
            k = scan_packed(ic[lc:], hc - lc, s, tb, base, flat, tab, cols, window_us, min_support, out, k, a)
            if hi < e:  # where the whole stream rebases; only this polarity's plane
                rebase(mine, min(t[hi] - base - low, {info.max - info.min + 1}), {info.min})
                base = t[hi] - low
            lo = hi
            lc = hc
    return base, k, {GOOD}
"""
    env: dict[str, Any] = {
        "np": np,
        "cnt": _count_ge_intrinsic(),
        "prefetch": _prefetch_intrinsic(),
        "rebase": _rebase,
        "prepare": _prepare,
        "collect": _collect,
        "pack": _pack,
    }
    output = ("split " if split else "") + ("events" if gather else "mask")
    name = f"<BAF kernel r={radius} update_on_drop={update_on_drop} {dtype} {output}>"
    exec(compile(src, name, "exec"), env)
    env["scan"] = njit(nogil=True, boundscheck=False)(env["scan"])
    env["scan_packed"] = njit(nogil=True, boundscheck=False)(env["scan_packed"])
    entry = "split_kernel" if split else "kernel"
    kernel: Callable[..., tuple[int, int, int]] = njit(nogil=True, boundscheck=False)(env[entry])
    return kernel


@njit(nogil=True, cache=True)
def _collect(  # pragma: no cover - numba
    x: NDArray[np.uint16],
    y: NDArray[np.uint16],
    p: NDArray[np.int8],
    t: NDArray[np.int64],
    idx: NDArray[np.int64],
    n: int,
    ox: NDArray[np.uint16],
    oy: NDArray[np.uint16],
    op: NDArray[np.int8],
    ot: NDArray[np.int64],
    k: int,
) -> int:
    """Append the events at idx[:n] to the o* arrays from position k; the new length. The caller
    allocates the outputs with numpy: on this project's VMs numba's own allocations of fresh memory
    took twice as long (page faults)."""
    for j in range(n):
        i = idx[j]
        ox[k + j] = x[i]
        oy[k + j] = y[i]
        op[k + j] = p[i]
        ot[k + j] = t[i]
    return k + n


@njit(nogil=True, cache=True)
def gather_merged(  # pragma: no cover - numba
    x: NDArray[np.uint16],
    y: NDArray[np.uint16],
    p: NDArray[np.int8],
    t: NDArray[np.int64],
    a: NDArray[np.int32],
    b: NDArray[np.int32],
    ox: NDArray[np.uint16],
    oy: NDArray[np.uint16],
    op: NDArray[np.int8],
    ot: NDArray[np.int64],
) -> None:
    """The events at the union of two ascending index lists, in stream order, in one pass. Each list
    ends with a sentinel above every index (not counted in the output's length), so the merge takes
    the smaller head without a branch."""
    i = np.int64(0)
    j = np.int64(0)
    for o in range(ox.shape[0]):
        ia = a[i]
        ib = b[j]
        take_a = ia < ib
        k = ia if take_a else ib
        i += np.int64(take_a)
        j += np.int64(not take_a)
        ox[o] = x[k]
        oy[o] = y[k]
        op[o] = p[k]
        ot[o] = t[k]


@njit(nogil=True, cache=True)
def scatter(keep: NDArray[np.bool_], idx: NDArray[np.int32]) -> None:  # pragma: no cover - numba
    """keep[i] = True for every i in idx (numpy's fancy assignment took ~3x as long)."""
    for j in range(idx.shape[0]):
        keep[idx[j]] = True


def on_two_threads(first: Callable[[], None], second: Callable[[], None], name: str) -> None:
    """Run `second` on a new thread and `first` here (both release the GIL in numba); re-raise
    what either raised, once both are done."""
    errors: list[BaseException] = []

    def run(fn: Callable[[], None]) -> None:
        try:
            fn()
        except BaseException as exc:  # noqa: BLE001 - re-raised on the calling thread below
            errors.append(exc)

    other = threading.Thread(target=run, args=(second,), name=name, daemon=True)
    other.start()
    run(first)
    other.join()
    if errors:
        raise errors[0]


def halves(off: NDArray[np.int32], on: NDArray[np.int32], n: int) -> tuple[int, int]:
    """Where each sentinel-ended index list crosses the chunk's middle: the merge splits there, so
    two threads each write one half of the output (and of a mask) without sharing a line."""
    mid = n // 2
    return int(np.searchsorted(off[:-1], mid)), int(np.searchsorted(on[:-1], mid))
