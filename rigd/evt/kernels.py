# mypy: disable-error-code="call-arg,arg-type"
"""Building blocks of the EVT numba kernels: the decode contract's types and the stores they share.

Every decode kernel has one signature, `kernel(buf, pos, end, st, out, n, nt, stats, cfg) ->
(pos, n, nt, err)` (see `evt3.decode_kernel`), so `StreamDecoder` drives any of them alike. The
helpers are `inline="always"`: numba pastes them into the calling kernel before LLVM optimises it,
so sharing them costs no call and keeps constant arguments (a one-pixel mask) foldable.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic
from numpy.typing import NDArray

from rigd.evt.errors import (
    JUMP_COUNT,
    JUMP_FIELDS,
    JUMP_REC,
    MAX_SKIP_OFFSETS,
    OK,
    OUT_OF_RANGE_XY,
    SKIP_COUNT,
    SKIP_POS,
)

U8 = NDArray[np.uint8]
U16 = NDArray[np.uint16]
U32 = NDArray[np.uint32]
I8 = NDArray[np.int8]
I64 = NDArray[np.int64]


# A decode kernel's outputs travel as one plain tuple, indexed by these names: events (x, y, p, t)
# filled from index n on, trigger edges (t, p, channel) from index nt on. Plain tuples rather than
# NamedTuples: numba's cache pickles a NamedTuple argument's class by name, and a cache written
# before that class were renamed would then fail to load (numba issue #6018).
X, Y, P, T, TRIG_T, TRIG_P, TRIG_CH = range(7)
DecodeOut = tuple[U16, U16, I8, I64, I64, U8, U8]
# What a decoder fixes for its stream: width, height, strict, final (no more bytes will come: a
# time jump still undecided is decided now), and how many TIME_HIGH values confirm a jump back.
DecodeConfig = tuple[int, int, bool, bool, int]
DecodeKernel = Callable[..., tuple[int, int, int, int]]

# A TIME_HIGH that falls (less than half the counter: not a roll-over) is a jump back in time
# when it is the first of JUMP_CONFIRM increasing TIME_HIGH values that all stay below the old
# one: a sensor re-based or two recordings joined. One corrupt word never is: the stream's next
# new TIME_HIGH value goes on from the old base (cameras repeat a value, then step it by one).
JUMP_CONFIRM = 2
# Words looked at after such a TIME_HIGH before it is judged a corrupt word: bounds what the
# decoder holds back while it decides (4 MiB of EVT 3.0, ~1000x a camera's TIME_HIGH period).
JUMP_LOOKAHEAD = 1 << 21
# What `jump_verdict`s say about such a TIME_HIGH.
JUMP_REJECT, JUMP_ACCEPT, JUMP_UNDECIDED = 0, 1, 2


def decode_config(
    width: int, height: int, strict: bool, *, final: bool = False, confirm: int = JUMP_CONFIRM
) -> DecodeConfig:
    return (int(width), int(height), bool(strict), bool(final), int(confirm))


def decode_out(n_events: int, n_triggers: int) -> DecodeOut:
    """Empty output arrays for that many events and trigger edges."""
    return (
        np.empty(n_events, np.uint16),
        np.empty(n_events, np.uint16),
        np.empty(n_events, np.int8),
        np.empty(n_events, np.int64),
        np.empty(n_triggers, np.int64),
        np.empty(n_triggers, np.uint8),
        np.empty(n_triggers, np.uint8),
    )


@intrinsic
def cttz(typingctx: object, x: types.Integer) -> object:
    """Count trailing zeros (one instruction): walks a validity mask's set bits without a
    data-dependent branch per bit."""
    sig = x(x)

    def codegen(context: object, builder: ir.IRBuilder, signature: object, args: list[ir.Value]) -> ir.Value:
        return builder.cttz(args[0], ir.Constant(ir.IntType(1), 0))

    return sig, codegen


@intrinsic
def ctpop(typingctx: object, x: types.Integer) -> object:
    """Population count (one instruction, vectorisable)."""
    sig = x(x)

    def codegen(context: object, builder: ir.IRBuilder, signature: object, args: list[ir.Value]) -> ir.Value:
        return builder.ctpop(args[0])

    return sig, codegen


@njit(inline="always")
def put_event(out: DecodeOut, n: int, x: int, y: int, p: int, t: int) -> None:  # pragma: no cover - numba
    """Store one event at index n (unsigned index: no negative-index wrap-around code)."""
    i = np.uint64(n)
    out[X][i] = x
    out[Y][i] = y
    out[P][i] = p
    out[T][i] = t


@njit(inline="always")
def put_run(out: DecodeOut, n: int, x0: int, m: int, y: int, p: int, t: int) -> int:  # pragma: no cover
    """Events at x0 + i for each set bit i of m, all known inside the sensor; returns the new n.

    The first store is unconditional and n advances by whether m had a bit, so the usual
    one-pixel mask costs no branch; slot n must exist even when m is 0."""
    put_event(out, n, x0 + cttz(m), y, p, t)
    n += np.int64(m != 0)
    m &= m - 1
    while m != 0:
        put_event(out, n, x0 + cttz(m), y, p, t)
        n += 1
        m &= m - 1
    return n


@njit(inline="always")
def skipped(stats: I64, code: int, count: int, pos: int) -> None:  # pragma: no cover - numba
    """Count `count` skipped items of kind `code` from the word at `pos`, whose position is kept
    while fewer than MAX_SKIP_OFFSETS were: a corrupt file's report can point at the bytes."""
    stats[code] += count
    k = stats[SKIP_COUNT]
    if k < MAX_SKIP_OFFSETS:
        stats[SKIP_POS + k] = pos
        stats[SKIP_COUNT] = k + 1


@njit(inline="always")
def last_time(times: I64, n: int, before: int) -> int:  # pragma: no cover - numba
    """Time of the last item stored (index n - 1), or `before` (the previous call's) if none."""
    return times[np.uint64(n - 1)] if n > 0 else before


@njit(inline="always")
def keep_last_times(st: I64, out: DecodeOut, n: int, nt: int) -> None:  # pragma: no cover - numba
    """Every decoder state ends with the times of the last event and trigger edge emitted; kept
    here on leaving a kernel, for the next call, whose outputs start empty."""
    k = st.shape[0]
    st[k - 2] = last_time(out[T], n, st[k - 2])
    st[k - 1] = last_time(out[TRIG_T], nt, st[k - 1])


@njit(inline="always")
def put_checked(  # pragma: no cover - numba
    out: DecodeOut, n: int, x0: int, m: int, y: int, p: int, t: int, stats: I64, cfg: DecodeConfig, pos: int
) -> tuple[int, bool]:
    """Events at x0 + i for each set bit i of m; pixels outside the sensor are counted as
    out_of_range_xy instead. Returns (new n, whether any pixel was outside)."""
    width = cfg[0]
    height = cfg[1]
    bad = 0
    while m != 0:
        x = x0 + cttz(m)
        m &= m - 1
        if x >= width or y >= height:
            bad += 1
        else:
            put_event(out, n, x, y, p, t)
            n += 1
    if bad:
        skipped(stats, OUT_OF_RANGE_XY, bad, pos)
    return n, bad != 0


@njit(inline="always")
def violation(stats: I64, code: int, strict: bool, pos: int) -> int:  # pragma: no cover - numba
    """Count one violation of kind `code` at word `pos`; returns the code when it stops the
    decoder (strict mode), else OK."""
    skipped(stats, code, 1, pos)
    return code if strict else OK


@njit(inline="always")
def put_trigger(out: DecodeOut, nt: int, t: int, p: int, channel: int) -> int:  # pragma: no cover
    """Store one trigger edge at index nt; returns nt + 1."""
    out[TRIG_T][nt] = t
    out[TRIG_P][nt] = p
    out[TRIG_CH][nt] = channel
    return nt + 1


@njit(inline="always")
def accept_jump(  # pragma: no cover - numba
    stats: I64, pos: int, loop_base: int, th: int, v: int, th_shift: int, shift: int, held: int
) -> int:
    """Accept a jump back of TIME_HIGH from `th` to `v` (a value counts 1 << `th_shift` us;
    `loop_base` is the loop's time): the new base goes on one period after the old one, so
    every later time is shifted further; the jump is kept for the decoder (a free slot is the
    caller's to check). The shift from here on."""
    shift += (th - v + 1) << th_shift
    k = stats[JUMP_COUNT]
    r = JUMP_REC + k * JUMP_FIELDS
    stats[r] = pos
    stats[r + 1] = loop_base | (th << th_shift)
    stats[r + 2] = loop_base | (v << th_shift)
    stats[r + 3] = shift
    stats[r + 4] = held
    stats[JUMP_COUNT] = k + 1
    return shift
