# mypy: disable-error-code="arg-type,call-arg,assignment"
"""EVT 3.0 scan: how many events a stretch of words holds and their first and last time, without
decoding them.

A capture that stores the words as sent (decision 0021) needs of each packet only its event
count, its time span and its trigger edges: the words go to the file, and the take's reader
decodes them. The scan follows the reference state machine's per-word semantics
(`evt3.decode_kernel`) for the words of a valid stream and stores nothing per event; like
`evt3_fast`, it walks a VECT_BASE_X's vectors in a loop of their own. Anything the decoder would
skip, drop or have to judge (an event before a time base or without a y, a pixel outside the
sensor, a time that would go back, a TIME_HIGH step beyond `TH_JUMP`, an unknown type, more
trigger edges than the buffer holds) makes the stretch not clean: the caller then decodes it
instead, so the count is the decoder's to the event (tests compare the two on random streams
and on the real Gen4.1 recording).

Measured on the real Gen4.1 words (one core, 28,000-word stretches, best of 15): 5.1-5.4 ns an
event, against 5.7-5.8 for the same loop without the vector run and 13-18 for a version whose
state updates were selects instead of branches (numba kept the branches and added the selects'
work); `evt3_fast.decode_kernel` took ~7.8 then, plus its output arrays.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from rigd.evt.evt3 import NOBASE, ST_TEV, ST_TTR, TH_JUMP, load_state, store_state
from rigd.evt.kernels import I64, U8, U16, ctpop

_U64 = np.uint64


@njit(nogil=True, cache=True)
def scan_kernel(
    buf: U16, st: I64, width: int, height: int, tt: I64, tp: U8, tc: U8
) -> tuple[bool, int, int, int, int]:
    """Scan the words buf[:] on from state `st`, which is updated in place.

    Returns (clean, events, first event time, last event time, trigger edges stored in tt/tp/tc).
    Not clean: the stretch holds a word the scan does not mirror, and `st` and the counts are
    meaningless (the caller scans on a copy and decodes instead)."""
    started, loop, th, y, base, vpol, shift, tcur = load_state(st)
    if started == 0:
        return False, 0, -1, -1, 0
    last_ev = st[ST_TEV]
    last_tr = st[ST_TTR]
    n = 0
    nt = 0
    t_first = -1
    end = buf.shape[0]
    pos = 0
    ok_y = 0 <= y < height
    while pos < end:
        w = np.int64(buf[_U64(pos)])
        typ = w >> 12
        if typ == 0x2:
            if not ok_y or (w & 0x7FF) >= width or tcur < last_ev:
                break
            if n == 0:
                t_first = tcur
            n += 1
            last_ev = tcur
        elif typ == 0x0:
            y = w & 0x7FF
            ok_y = y < height
        elif typ == 0x4 or typ == 0x5:
            if base >= NOBASE or y < 0:
                break
            m = w & (0xFFF if typ == 0x4 else 0xFF)
            if m != 0:
                room = width - base
                if not ok_y or tcur < last_ev or room <= 0 or (room < 12 and (m >> room) != 0):
                    break
                if n == 0:
                    t_first = tcur
                n += ctpop(m)
                last_ev = tcur
            base += 12 if typ == 0x4 else 8
        elif typ == 0x6:
            tcur = (tcur & ~0xFFF) | (w & 0xFFF)
        elif typ == 0x3:
            base = w & 0x7FF
            vpol = 1 if (w & 0x800) != 0 else -1
            # the usual run: vectors right after their base, on one y inside the sensor
            if ok_y and tcur >= last_ev:
                while pos + 1 < end:
                    w2 = np.int64(buf[_U64(pos + 1)])
                    t2 = w2 >> 12
                    if t2 != 0x4 and t2 != 0x5:
                        break
                    m = w2 & (0xFFF if t2 == 0x4 else 0xFF)
                    room = width - base
                    if room < 12 and (room <= 0 or (m >> room) != 0):
                        break
                    if m != 0:
                        if n == 0:
                            t_first = tcur
                        n += ctpop(m)
                        last_ev = tcur
                    base += 12 if t2 == 0x4 else 8
                    pos += 1
        elif typ == 0x8:
            v12 = w & 0xFFF
            fell = v12 < th
            if fell and th - v12 < 2048:
                break
            if (v12 - th) + (4096 if fell else 0) > TH_JUMP:
                break
            if fell:
                loop += 1
            th = v12
            tcur = ((loop << 24) | (th << 12)) + shift
        elif typ == 0xA:
            if tcur < last_tr or nt >= tt.shape[0]:
                break
            tt[nt] = tcur
            tp[nt] = w & 1
            tc[nt] = (w >> 8) & 0xF
            nt += 1
            last_tr = tcur
        elif typ == 0x7 or typ == 0xE or typ == 0xF:
            pass
        else:
            break
        pos += 1
    if pos < end:
        return False, 0, -1, -1, 0
    store_state(st, started, loop, th, tcur, y, base, vpol)
    st[ST_TEV] = last_ev
    st[ST_TTR] = last_tr
    return True, n, t_first, last_ev, nt
