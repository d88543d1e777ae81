# mypy: disable-error-code="arg-type,call-arg"
"""EVT 3.0 decode kernel for clean stretches of a stream, with `evt3.decode_kernel` as fallback.

Same signature, state array and results as `evt3.decode_kernel` (events, order, triggers, stats,
strict-mode error word, outgoing state), so `StreamDecoder` can use either and chunk boundaries
carry state exactly as before.

While the decoder state is "clean" (a TIME_HIGH was seen, the current y is inside the sensor) the
loop dispatches on the word type with ordinary branches and handles only what cannot violate the
format: an ADDR_X inside the width, a vector whose whole 12/8-pixel span lies inside the width,
ADDR_Y inside the height, VECT_BASE_X, a TIME_LOW or TIME_HIGH that does not take the time back,
triggers not earlier than the last one, and the ignored types 7/E/F; it runs only while the time
is at or past the last emitted event's, so its events never go back in time. Any other word (or a
state that is not clean) hands a short window of words to the reference state machine, which
counts/raises exactly as it always did, and the fast loop resumes from the state it leaves.
Output capacity is checked once per block of words (12 events per word at most) instead of once
per word.

What a Gen4 sends (the real Gen4.1 recording: ADDR_X 64 % of the words, ADDR_Y 19 %, vectors
14 %, TIME_LOW 2.9 %, TIME_HIGH 0.2 %, of which 548 in 551 repeat the value before) runs in one
loop: ADDR_Y/ADDR_X branch-free, TIME_LOW and the vector group (VECT_BASE_X, VECT_12, VECT_12,
VECT_8: 32 pixels as one mask, `_group`) as rarely taken branches inside it. A repeated TIME_HIGH
resets TIME_LOW to 0, which takes the time back until the TIME_LOW that follows it: the pair is
taken together here (left to the reference kernel, each repeat cost a window of slow words: a
fifth of the decode). The encoder's (VECT_BASE_X, vector) pairs are decoded in a loop of their
own inside the dispatch's VECT_BASE_X branch (-7% kernel time on the encoder's stream); the
vector base and polarity share one register (base << 8 | pol byte) and loop/TIME_HIGH live
inside the packed time. Measured and rejected: folding ADDR_X after an ADDR_Y into its branch
(4-14% slower), TIME_LOW as selects in the ADDR_Y/ADDR_X path (+25 %: ~8 more instructions on
every word cost more than one mispredict per TIME_LOW), and one generic vector loop inside the
run loop (register pressure spilled the word position; the encoder's stream +10 %).

Measured against the branch-free reference loop (one core, re-encoded Gen4.1 recording): ~25%
less kernel time, because a valid stream's type sequence is predictable enough that a few
mispredicted branches cost less than the reference's ~50 masked-merge instructions per word.
A data-parallel split (phase 1: per-word prefix state into a cache-resident block; phase 2:
expansion) was measured too and was ~15% *slower* than the reference: it does the same state
merges plus the stores/reloads of the intermediate state.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from rigd.evt.evt3 import NOBASE, ST_SHIFT, ST_TEV, ST_TTR, TH_JUMP
from rigd.evt.evt3 import decode_kernel as reference_kernel
from rigd.evt.kernels import (
    I64,
    TRIG_T,
    U16,
    DecodeConfig,
    DecodeOut,
    T,
    X,
    ctpop,
    cttz,
    keep_last_times,
    last_time,
    put_event,
    put_run,
    put_trigger,
)

_U64 = np.uint64
_WINDOW = 64  # words handed to the reference kernel per irregular stretch
# the run loop's types: ADDR_Y, ADDR_X, TIME_LOW; it goes on through VECT_BASE_X too (a Gen4's
# vector group)
_RUN = (1 << 0x0) | (1 << 0x2) | (1 << 0x6)
_XYT = _RUN | (1 << 0x3)


@njit(inline="always")
def _group(buf: U16, pos: int, out: DecodeOut, n: int, y: int, bp: int, t: int) -> int:  # pragma: no cover
    """The events of a Gen4's usual vector group after the VECT_BASE_X at `pos`: VECT_12, VECT_12,
    VECT_8 (32 pixels, all inside the sensor: the caller checked the base), or -1 when the next
    three words are not that group. Its 32-bit mask has, nearly always, 2 pixels set: two stores
    whatever the count (the slots exist), a loop only for more. Returns the new n."""
    w1 = np.int64(buf[_U64(pos + 1)])
    w2 = np.int64(buf[_U64(pos + 2)])
    w3 = np.int64(buf[_U64(pos + 3)])
    if ((w1 >> 4) & 0xF00) | ((w2 >> 8) & 0xF0) | (w3 >> 12) != 0x445:
        return -1
    m = (w1 & 0xFFF) | ((w2 & 0xFFF) << 12) | ((w3 & 0xFF) << 24)
    x0 = bp >> 8
    put_event(out, n, x0 + cttz(m), y, bp, t)
    m &= m - 1
    put_event(out, n + 1, x0 + cttz(m), y, bp, t)
    m &= m - 1
    k = n + 2
    while m != 0:
        put_event(out, k, x0 + cttz(m), y, bp, t)
        k += 1
        m &= m - 1
    return n + ctpop(w1 & 0xFFF) + ctpop(w2 & 0xFFF) + ctpop(w3 & 0xFF)


# Kept apart from the reference `evt3.decode_kernel` on purpose: that branch-free state machine
# is this kernel's oracle in the tests and its fallback for every irregular word, and the two
# loops' shapes are what make one fast and the other exact (measurements above); what they share
# (event, run and trigger stores) lives in `kernels`.
@njit(nogil=True, cache=True)
def decode_kernel(
    buf: U16, pos: int, end: int, st: I64, out: DecodeOut, n: int, nt: int, stats: I64, cfg: DecodeConfig
) -> tuple[int, int, int, int]:
    """Decode words buf[pos:end]; contract of `evt3.decode_kernel` (returns (pos, n, nt, err))."""
    width = cfg[0]
    height = cfg[1]
    cap = out[X].shape[0] - 12
    tcap = out[TRIG_T].shape[0]
    # vector base and polarity packed in one register: bp = base << 8 | (vpol & 0xFF); the int8
    # store of bp is the polarity, bp >> 8 the base; one compare checks "base given and whole span
    # inside the width" (the no-base sentinel is larger than any packed base)
    bplim = ((width - 12) << 8) | 0xFF
    while pos < end:
        y = st[4]
        # time packed as loop << 24 | TIME_HIGH << 12 | TIME_LOW, plus the shift of the jumps back
        # accepted so far (whole 4096 us periods); TIME_HIGH and loop derived from it less the shift
        sh = st[ST_SHIFT]
        tcur = ((st[1] << 24) | (st[2] << 12) | st[3]) + sh
        bp = (st[5] << 8) | (st[6] & 0xFF) if st[5] >= 0 else NOBASE
        if st[0] != 0 and 0 <= y < height and tcur >= last_time(out[T], n, st[ST_TEV]):
            while pos < end:
                bend = min(end, pos + (cap - n) // 12)  # no capacity check inside the block
                if bend <= pos:
                    break
                while pos < bend:
                    w = np.int64(buf[_U64(pos)])
                    typ = w >> 12
                    if (_RUN >> typ) & 1:
                        # ADDR_Y / ADDR_X / TIME_LOW runs (a Gen4 sends mostly single ADDR_X
                        # events under an ADDR_Y, a TIME_LOW every few dozen words): one loop
                        # where the pattern of Y and X words, which no predictor learns, only
                        # selects values, and a TIME_LOW is a rarely taken branch inside it (not
                        # a way out and back in: that cost ~60 cycles a TIME_LOW). Every X or Y
                        # word stores an event at n (slot n exists: 12 per word are free); only
                        # an ADDR_X advances n, only an ADDR_Y moves y.
                        bad = False
                        while True:
                            if (w & 0xD000) == 0:  # ADDR_Y or ADDR_X: one test, the usual way
                                v = w & 0x7FF
                                isx = int((w >> 13) & 1)
                                if v >= (width if isx else height):
                                    bad = True  # outside the sensor: the reference counts it
                                    break
                                put_event(out, n, v, y, ((w >> 10) & 2) - 1, tcur)
                                n += isx
                                y = y if isx else v  # a select: y is the loop's carried value
                            elif (w >> 12) == 0x6:
                                tl = w & 0xFFF
                                if tl < (tcur & 0xFFF):
                                    bad = True  # time falls: the reference drops what would go back
                                    break
                                tcur = (tcur & ~0xFFF) | tl
                            elif (w >> 12) == 0x3:
                                # VECT_BASE_X: the Gen4's group stays in this loop; any other
                                # vectors are the dispatch's (the encoder's pairs)
                                b = w & 0x7FF
                                vp = (((w >> 10) & 2) + 0xFF) & 0xFF
                                if pos + 3 >= bend or b > width - 32:
                                    break
                                k = _group(buf, pos, out, n, y, (b << 8) | vp, tcur)
                                if k < 0:
                                    break
                                n = k
                                bp = ((b + 32) << 8) | vp
                                pos += 3
                            else:
                                break
                            pos += 1
                            if pos >= bend:
                                break
                            w = np.int64(buf[_U64(pos)])
                        if bad:
                            break
                        continue
                    elif typ == 0x3:
                        # the encoder's usual run: (VECT_BASE_X, vector) pairs, decoded here in a
                        # loop of their own so the type dispatch sees fewer, more predictable words
                        while True:
                            bp = ((w & 0x7FF) << 8) | (((w >> 10) & 2) + 0xFF) & 0xFF
                            if pos + 1 >= bend or bp > bplim:
                                break
                            w2 = np.int64(buf[_U64(pos + 1)])
                            t2 = w2 >> 12
                            if t2 != 0x4 and t2 != 0x5:
                                break
                            n = put_run(out, n, bp >> 8, w2 & (0xFFF if t2 == 0x4 else 0xFF), y, bp, tcur)
                            bp += (12 << 8) if t2 == 0x4 else (8 << 8)
                            pos += 1  # at the vector word
                            if pos + 1 >= bend:
                                break
                            w = np.int64(buf[_U64(pos + 1)])
                            if (w >> 12) != 0x3:
                                break
                            pos += 1  # at the next VECT_BASE_X
                    elif typ == 0x4 or typ == 0x5:
                        if bp > bplim:  # no base, or a span reaching past the width
                            break
                        n = put_run(out, n, bp >> 8, w & (0xFFF if typ == 0x4 else 0xFF), y, bp, tcur)
                        bp += (12 << 8) if typ == 0x4 else (8 << 8)
                    elif typ == 0x8:
                        v12 = w & 0xFFF
                        traw = tcur - sh
                        th = (traw >> 12) & 0xFFF
                        tnew = (traw & ~0xFFFFFF) | (v12 << 12)
                        if v12 < th:
                            if th - v12 < 2048:
                                break  # a jump back or a corrupt word: the reference tells which
                            tnew += 1 << 24
                        elif tnew < traw:
                            # the same TIME_HIGH again (a Gen4 repeats it, nearly all its TIME_HIGHs
                            # are repeats) takes TIME_LOW back to 0, and the TIME_LOW that always
                            # follows takes it on: time goes back only when that one is lower (or
                            # another word comes first), and the reference handles it then. Left
                            # to the reference, each repeat cost a window of its slow words (a
                            # fifth of the decode on the Gen4.1 recording).
                            if pos + 1 >= bend:
                                break
                            w2 = np.int64(buf[_U64(pos + 1)])
                            if (w2 >> 12) != 0x6 or (w2 & 0xFFF) < (traw & 0xFFF):
                                break
                            tnew |= w2 & 0xFFF
                            pos += 1
                        if (tnew >> 12) - (traw >> 12) > TH_JUMP:
                            break  # a jump: the reference checks it against the next TIME_HIGH
                        tcur = tnew + sh
                    elif typ == 0xA:
                        if nt >= tcap or tcur < last_time(out[TRIG_T], nt, st[ST_TTR]):
                            break
                        nt = put_trigger(out, nt, tcur, w & 1, (w >> 8) & 0xF)
                    elif typ == 0x7 or typ >= 0xE:
                        pass
                    else:
                        break  # unknown type
                    pos += 1
                if pos < bend:
                    break
            traw = tcur - sh
            st[1] = traw >> 24
            st[2] = (traw >> 12) & 0xFFF
            st[3] = traw & 0xFFF
            st[4] = y
            if bp < NOBASE:
                st[5] = bp >> 8
                st[6] = np.int64(np.int8(bp & 0xFF))
            else:
                st[5] = -1
        if pos >= end:
            break
        # irregular word, state not clean, or outputs nearly full: reference semantics
        wend = min(end, pos + _WINDOW)
        pos, n, nt, err = reference_kernel(buf, pos, wend, st, out, n, nt, stats, cfg)
        if err != 0 or pos < wend:
            return pos, n, nt, err
    keep_last_times(st, out, n, nt)
    return pos, n, nt, 0
