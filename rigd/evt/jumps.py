"""Time jumps back that a decoder accepted: where they are and what they did to the times.

A stream whose TIME_HIGH falls and then goes on rising from the lower value (two recordings
joined, a sensor re-based a few ms back) is not corrupt: the kernels accept the jump, shift every
later time so that the new base follows the old one, and leave a record in their stats array
(`errors.JUMP_REC`). This module turns those records into `TimeJump`s and the counters that the
capture path and `rigd convert` write into the take.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rigd.evt.errors import JUMP_COUNT, JUMP_FIELDS, JUMP_REC

# accepted jumps a decoder keeps in full (all are counted); like its first skipped offsets
MAX_KEPT_JUMPS = 16


@dataclass(frozen=True, slots=True)
class TimeJump:
    """One accepted jump back. Bases are the stream's own clock (its TIME_HIGH times, us);
    `shift_us` is what the decoder adds to every time from here on (all earlier jumps included)."""

    offset: int
    """Absolute byte offset of the TIME_HIGH word that jumped."""
    old_base_us: int
    new_base_us: int
    shift_us: int
    held_events: int
    """Events between the jump and the TIME_HIGH that confirmed it: decoded and kept."""

    def line(self, fmt: str) -> str:
        """The jump in one line, for logs and the take's warnings."""
        return (
            f"{fmt} stream time jumped back at byte offset {self.offset}: TIME_HIGH base "
            f"{self.old_base_us} us -> {self.new_base_us} us; later times shifted by +{self.shift_us} us "
            f"to follow on; {self.held_events} event(s) decoded while confirming it, all kept"
        )


def take_jumps(stats: NDArray[np.int64], abs_start: int, word_bytes: int) -> list[TimeJump]:
    """The records a kernel call left (word positions made absolute byte offsets); empties them."""
    jumps = []
    for k in range(int(stats[JUMP_COUNT])):
        pos, old, new, shift, held = (int(v) for v in stats[JUMP_REC + k * JUMP_FIELDS :][:JUMP_FIELDS])
        jumps.append(TimeJump(abs_start + pos * word_bytes, old, new, shift, held))
    stats[JUMP_COUNT] = 0
    return jumps


def jump_counters(jumps: list[TimeJump], count: int, held: int) -> dict[str, int]:
    """Counters of the jumps a decoder accepted (`count` of them, `held` events kept while
    confirming them), with where the first was; empty when there was none."""
    if not count:
        return {}
    first = jumps[0]
    return {
        "time_jumps": count,
        "time_jump_held_events": held,
        "time_jump_first_offset": first.offset,
        "time_jump_first_old_base_us": first.old_base_us,
        "time_jump_first_new_base_us": first.new_base_us,
        "time_jump_first_shift_us": first.shift_us,
    }
