"""Decode-error type and the names of the violations the EVT decoders count or raise.

The numba kernels cannot raise rich exceptions, so they report a small integer code and the
byte position of the offending word; this module maps codes to stable names that appear both
in `StreamDecoder.stats` (tolerant mode) and in `EvtDecodeError.kind` (strict mode).
"""

from __future__ import annotations

from rigd.core.errors import EventDataError

# Codes shared by every kernel; index into the kernels' int64 stats array.
OK = 0
NON_MONOTONIC_TIME_HIGH = 1
VECTOR_WITHOUT_BASE = 2
OUT_OF_RANGE_XY = 3
UNKNOWN_TYPE = 4
TRUNCATED = 5
BEFORE_TIME_HIGH = 6
EVENT_WITHOUT_Y = 7
NON_MONOTONIC_TIME = 8  # an event or trigger edge whose time would fall below the last one emitted
TIME_HIGH_JUMP = 9  # a TIME_HIGH jumping away (or "rolling over") that the next one contradicts
N_CODES = 10
# After the codes, the stats array keeps the word positions of the first few skipped items (see
# `kernels.skipped`): slot SKIP_COUNT counts them, SKIP_POS.. holds them; the decoder turns them
# into absolute byte offsets after each kernel call.
MAX_SKIP_OFFSETS = 8
SKIP_COUNT = N_CODES
SKIP_POS = N_CODES + 1
# Then the time jumps a kernel accepted in this call (see `kernels.accept_jump`): slot JUMP_COUNT
# counts them, JUMP_REC.. holds JUMP_FIELDS values each (word position, old and new TIME_HIGH base
# on the stream's clock, the shift applied from there on, events decoded while confirming). A
# kernel whose slots are full stops before the next jump; the decoder empties them after each call.
MAX_JUMP_RECORDS = 4
JUMP_FIELDS = 5
JUMP_COUNT = SKIP_POS + MAX_SKIP_OFFSETS
JUMP_REC = JUMP_COUNT + 1
STATS_SIZE = JUMP_REC + MAX_JUMP_RECORDS * JUMP_FIELDS

# Not a violation: a kernel returns HOLD (with the position of a TIME_HIGH that falls) when the
# words it has do not yet tell a time jump from a corrupt word; the decoder keeps the words from
# there and decodes them with the next bytes (or at the end of the stream, see `StreamDecoder`).
HOLD = 100

KIND_NAMES: dict[int, str] = {
    NON_MONOTONIC_TIME_HIGH: "non_monotonic_time_high",
    VECTOR_WITHOUT_BASE: "vector_without_base",
    OUT_OF_RANGE_XY: "out_of_range_xy",
    UNKNOWN_TYPE: "unknown_type",
    TRUNCATED: "truncated",
    BEFORE_TIME_HIGH: "before_time_high",
    EVENT_WITHOUT_Y: "event_without_y",
    NON_MONOTONIC_TIME: "non_monotonic_time",
    TIME_HIGH_JUMP: "time_high_jump",
}

# Kinds that strict mode does NOT raise on: a stream joined mid-way (before its first TIME_HIGH)
# is how every live capture starts, so OpenEB silently skips those words; we skip and count them.
NON_FATAL_KINDS = frozenset({BEFORE_TIME_HIGH})


class EvtDecodeError(EventDataError):
    """An EVT byte stream violates its format; `offset` is the absolute byte offset of the word."""

    def __init__(self, message: str, *, offset: int, kind: str) -> None:
        super().__init__(message)
        self.offset = offset
        self.kind = kind
