"""A RAW recording's EVT bytes held in memory as a device's byte stream: time at byte offsets,
an endless loop of whole TIME_HIGH periods, and the host-clock pace it is handed out at.

What a real sensor costs the host is its bytes arriving in memory, paced, and their decode.
`EvtFileStream` holds the file's stream once (read at open), knows the stream time at byte
offsets (`rigd.evt.timepoints`), and cuts it at word boundaries where everything before the
cut is due. With `loop`, an EVT 3.0 stream repeats a whole number of TIME_HIGH periods (4096 us)
that starts at the first TIME_HIGH word of a period; pass p adds the periods before it to every
TIME_HIGH word of the pass (mod 4096, the decoder follows the 24-bit wrap), so the looped stream
is a valid stream whose time keeps rising. Those are the recording's periods of the passes
before, and, where a real-clock `Pace` thins the events, quiet periods after each pass (no word
at all: the next pass's TIME_HIGH steps over them), spread so that the events come at the
pace's density while the clock keeps real time. The pass must not lean on
what came before it: its first event word comes after an ADDR_Y of the pass and its first
vector after a VECT_BASE_X of the pass (the real Gen4.1 sample opens every period with
TIME_HIGH, TIME_LOW, ADDR_Y), so every pass decodes to the same events shifted in time.
"""

from __future__ import annotations

import bisect
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from rigd.core.errors import ConfigError
from rigd.evt.timepoints import GRAIN_US, WORDS, time_points

log = logging.getLogger(__name__)

#: One EVT 3.0 TIME_HIGH period (us): the unit a looped EVT 3.0 stream repeats.
TH_PERIOD_US = 4096
_TH, _TL, _ADDR_Y, _BASE_X = 0x8, 0x6, 0x0, 0x3
_EVENT_TYPES = (0x2, 0x4, 0x5)
_VECTOR_TYPES = (0x4, 0x5)


@dataclass(frozen=True, slots=True)
class Pace:
    """Stream time against host time: `pace` x real time (0: unpaced), and an optional burst:
    from `burst_at_s` of host time on, for `burst_s`, `burst_pace` instead.

    `real_clock` (a looped stream, which can space its passes out): the stream's clock never
    runs slower than the host's; a pace below 1 thins the events instead (`density`), as a
    device at a lower event rate does. Above 1 the clock runs faster: the recording has no more
    events per microsecond to give."""

    pace: float = 0.0
    burst_at_s: float = 0.0
    burst_s: float = 0.0
    burst_pace: float = 0.0
    real_clock: bool = False

    def __post_init__(self) -> None:
        for name in ("pace", "burst_at_s", "burst_s", "burst_pace"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"replay pace: {name} must be a finite number >= 0, got {v}")
        if self.burst_s and (self.pace == 0 or self.burst_pace == 0):
            raise ConfigError("replay pace: a burst needs pace > 0 and a burst pace > 0")

    @property
    def paced(self) -> bool:
        return self.pace > 0

    def _paces(self) -> list[tuple[float, float, float]]:
        """(host start s, host end s, pace) of each phase."""
        if not self.burst_s:
            return [(0.0, math.inf, self.pace)]
        a, b = self.burst_at_s, self.burst_at_s + self.burst_s
        return [(0.0, a, self.pace), (a, b, self.burst_pace), (b, math.inf, self.pace)]

    def _phases(self) -> list[tuple[float, float, float]]:
        """(host start s, host end s, clock rate) of each phase."""
        return [(lo, hi, max(1.0, p) if self.real_clock else p) for lo, hi, p in self._paces()]

    def density(self, stream_us: int) -> float:
        """Events per recorded event at stream time `stream_us` (1 but for a real clock's
        pace below 1)."""
        if not self.real_clock or not self.paced:
            return 1.0
        h = self.host_s(stream_us)
        return min(1.0, next(p for lo, hi, p in self._paces() if lo <= h < hi))

    def stream_us(self, elapsed_s: float) -> int:
        """Stream time (us since the stream's start) due after `elapsed_s` of host time."""
        total = 0.0
        for lo, hi, p in self._phases():
            if elapsed_s <= lo:
                break
            total += (min(elapsed_s, hi) - lo) * p
        return int(total * 1e6)

    def host_s(self, stream_us: int) -> float:
        """Host time (s since start) at which `stream_us` becomes due."""
        target = stream_us / 1e6
        done = 0.0
        for lo, hi, p in self._phases():
            span = (hi - lo) * p
            if done + span >= target:
                return lo + (target - done) / p
            done += span
        return math.inf  # pragma: no cover - the last phase is endless


class EvtFileStream:
    """The stream of a RAW file (EVT 3.0, or EVT 2.0 without loop) in memory, as one endless
    (`loop`) or finite byte sequence; offsets count from the stream's first byte."""

    def __init__(
        self, path: Path, header_size: int, fmt: str, *, loop: bool, pace: Pace | None = None
    ) -> None:
        if fmt not in WORDS or (loop and fmt != "evt3"):
            raise ConfigError(f"event file {path}: no wire-byte replay of {fmt} (loop={int(loop)})")
        self.fmt = fmt
        self.loop = loop
        ws, dtype = WORDS[fmt]
        with path.open("rb") as f:
            f.seek(header_size)
            data = np.empty(max(0, os.fstat(f.fileno()).st_size - header_size), np.uint8)
            data = data[: f.readinto(data.data)]
        self.word_bytes = ws
        words = data[: len(data) // ws * ws].view(dtype)
        all_off, all_t, all_last = time_points(words, fmt)
        self.recorded_us = all_last - int(all_t[0]) if len(all_t) else 0
        self.period_us = 0
        self._th_pos = np.empty(0, np.int64)
        self._th_val = np.empty(0, np.int64)
        self._periods = 0
        if loop:
            start, end, periods = _loop_region(path, words)
            body = data[start * ws : end * ws].copy()
            self._periods = periods
            self.period_us = periods * TH_PERIOD_US
            region = body.view(dtype)
            self._th_pos = np.flatnonzero((region >> 12) == _TH)
            self._th_val = (region[self._th_pos] & 0xFFF).astype(np.int64)
            off, tp, _ = time_points(region, fmt)
            off, tp = np.append(off, len(body)), np.append(tp - tp[0], self.period_us)
        else:
            body = data
            off, tp, last = all_off, all_t, all_last
            if len(off):
                t0 = int(tp[0])
                off[0] = 0  # words before the first time word go with it (the decoder skips them)
                off = np.append(off, len(body))
                tp = np.append(tp - t0, (last - t0) // GRAIN_US * GRAIN_US + GRAIN_US)
            else:  # no time word: nothing to pace by, all of it is due at once
                off, tp = np.array([0, len(body)], np.int64), np.array([0, 0], np.int64)
        self._body = body
        self._off, self._t = off, tp
        self.span_bytes = len(body)
        self._pass_cache: tuple[int, NDArray[np.uint8]] = (0, body)
        self._pace = pace
        self._starts = [0]
        """TIME_HIGH periods before each pass (loop): its recording's periods, and quiet ones
        after it where the pace thins the events (`Pace.density`)."""
        self._quiet = 0.0  # quiet periods owed but not yet whole

    def _start_us(self, p: int) -> int:
        """Stream time at which pass p starts (loop)."""
        starts = self._starts
        while len(starts) <= p:
            prev = starts[-1]
            extra = 0
            if self._pace is not None:
                d = self._pace.density(prev * TH_PERIOD_US)
                self._quiet += self._periods * (1.0 / d - 1.0)
                extra = int(self._quiet)
                self._quiet -= extra
            starts.append(prev + self._periods + extra)
        return starts[p] * TH_PERIOD_US

    def _pass_at_us(self, due_us: int) -> int:
        """The last pass that starts at or before `due_us` (loop)."""
        while self._start_us(len(self._starts) - 1) <= due_us:
            self._start_us(len(self._starts))
        return bisect.bisect_right(self._starts, due_us // TH_PERIOD_US) - 1

    @property
    def end(self) -> int | None:
        """Bytes in the stream; None when it loops."""
        return None if self.loop else self.span_bytes

    def cut(self, due_us: int) -> int:
        """The furthest offset before which every byte's time is at most `due_us` (us since
        the stream's first time)."""
        if due_us < 0:
            return 0
        if not self.loop:
            k = int(np.searchsorted(self._t, due_us + 1, side="right")) - 1
            return int(self._off[max(k, 0)])
        p = self._pass_at_us(due_us)
        r = due_us - self._start_us(p)  # past the pass's own span: in its quiet periods, all due
        k = int(np.searchsorted(self._t, r + 1, side="right")) - 1
        return p * self.span_bytes + int(self._off[k])

    def next_due_us(self, pos: int) -> int | None:
        """The stream time at which bytes beyond `pos` become due; None past the end."""
        if not self.loop:
            if pos >= self.span_bytes:
                return None
            k = int(np.searchsorted(self._off, pos, side="right"))
            return int(self._t[min(k, len(self._t) - 1)]) - 1
        p, r = divmod(pos, self.span_bytes)
        k = int(np.searchsorted(self._off, r, side="right"))
        return self._start_us(p) + int(self._t[k]) - 1

    def due_at_us(self, pos: int) -> int:
        """The stream time from which the bytes before `pos` are all due (when a device would
        have had them in memory)."""
        if not self.loop:
            k = int(np.searchsorted(self._off, pos, side="left"))
            return int(self._t[min(k, len(self._t) - 1)]) - 1
        p, r = divmod(pos, self.span_bytes)
        k = int(np.searchsorted(self._off, r, side="left"))
        return max(0, self._start_us(p) + int(self._t[k]) - 1)

    def passes_at(self, pos: int) -> int:
        """Passes begun once `pos` bytes were handed out (1 for a stream that does not loop)."""
        if not self.loop or pos <= 0:
            return 1
        return (pos - 1) // self.span_bytes + 1

    def read(self, start: int, end: int) -> bytes:
        """The stream's bytes [start, end)."""
        if not self.loop:
            return self._body[start:end].tobytes()
        parts = []
        while start < end:
            p, r = divmod(start, self.span_bytes)
            n = min(end - start, self.span_bytes - r)
            parts.append(self._pass(p)[r : r + n].tobytes())  # copied before the next pass
            start += n
        return b"".join(parts) if len(parts) > 1 else parts[0]

    def _pass(self, p: int) -> NDArray[np.uint8]:
        """Pass p's bytes: the region with p x periods added to its TIME_HIGH words. One
        buffer serves every pass (only its TIME_HIGH words change), so a pass costs a few word
        writes, not a copy of the recording: what a device's own buffer costs the host."""
        cached, buf = self._pass_cache
        if cached == p:
            return buf
        if buf is self._body:  # the recording itself stays as read
            buf = self._body.copy()
        words = buf.view(WORDS[self.fmt][1])
        words[self._th_pos] = (_TH << 12) | ((self._th_val + self._start_us(p) // TH_PERIOD_US) & 0xFFF)
        self._pass_cache = (p, buf)
        return buf


def _loop_region(path: Path, words: NDArray[np.uint16]) -> tuple[int, int, int]:
    """(first word, end word, TIME_HIGH periods) of the EVT 3.0 loop: from the first TIME_HIGH
    word of a period whose pass stands alone, through the last whole period."""
    typ = (words >> 12).astype(np.int64)
    th_pos = np.flatnonzero(typ == _TH)
    vals = (words[th_pos] & 0xFFF).astype(np.int64)
    if len(vals) < 2:
        raise ConfigError(f"event file {path}: loop=1 needs a whole TIME_HIGH period; the recording has none")
    step = np.diff(vals)
    rolled = step <= -2048
    if ((step < 0) & ~rolled).any():
        raise ConfigError(
            f"event file {path}: loop=1 needs a stream whose time never falls back; TIME_HIGH falls at "
            f"byte {int(th_pos[1:][(step < 0) & ~rolled][0]) * 2} of the stream"
        )
    full = vals + np.concatenate([[0], np.cumsum(rolled)]) * 4096
    firsts = np.flatnonzero(np.concatenate([[True], np.diff(full) > 0]))  # each period's first TH
    ys, evs = np.flatnonzero(typ == _ADDR_Y), np.flatnonzero(np.isin(typ, _EVENT_TYPES))
    bases, vecs = np.flatnonzero(typ == _BASE_X), np.flatnonzero(np.isin(typ, _VECTOR_TYPES))
    for i in firsts[:-1]:
        s = int(th_pos[i])
        if _first_at(ys, s) <= _first_at(evs, s) and _first_at(bases, s) <= _first_at(vecs, s):
            periods = int(full[-1] - full[i])
            end = int(th_pos[np.searchsorted(full, full[-1])])
            log.debug("%s: loop of %d TIME_HIGH period(s) from word %d to %d", path, periods, s, end)
            return s, end, periods
    raise ConfigError(
        f"event file {path}: loop=1 found no TIME_HIGH period start whose events do not use an "
        "ADDR_Y or VECT_BASE_X from before it; the recording cannot loop as a valid stream"
    )


def _first_at(idx: NDArray[np.int64], start: int) -> int:
    """The first of the sorted word indices at or after start (a large number when none)."""
    k = int(np.searchsorted(idx, start))
    return int(idx[k]) if k < len(idx) else 1 << 62
