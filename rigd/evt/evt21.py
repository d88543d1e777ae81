"""EVT 2.1 (64-bit words, 32-pixel validity masks) decoder kernels and encoder, OpenEB semantics.

Each 64-bit word has its type, ts (6 bits), x base (11 bits) and y (11 bits) in the upper 32 bits
(same bit positions as EVT 2.0) and a 32-bit validity mask in the lower 32 bits: pixel
x_base + i fired when bit i is set. Two byte layouts exist: IMX636 sends the upper half first
(each half little-endian, "half-swapped", fmt "evt21"); GenX320 sends the whole 64-bit word
little-endian (lower half first, fmt "evt21_le"). Time handling is EVT 2.0's, and so are the
kernels: `evt2`'s factories built for masked words.
"""

from __future__ import annotations

import numpy as np

from rigd.core.events import EventArray, TriggerEvents
from rigd.evt import evt2
from rigd.evt.encoder import StreamEncoder

WORD_BYTES = 8
MAX_EVENTS_PER_WORD = 32
STATE_SIZE = evt2.STATE_SIZE
new_decoder_state = evt2.new_decoder_state  # EVT 2.0's time state: started, loop, time_high

# the kernels read a word as two u32 halves: buf[2 * pos], buf[2 * pos + 1]
decode_kernel = evt2.make_decode_kernel(masked=True, swapped=True)
decode_kernel_le = evt2.make_decode_kernel(masked=True, swapped=False)
encode_kernel = evt2.make_encode_kernel(masked=True, swapped=True)
encode_kernel_le = evt2.make_encode_kernel(masked=True, swapped=False)


class Evt21Encoder(StreamEncoder):
    """Streaming EVT 2.1 encoder (IMX636 half-swapped layout unless little_endian=True)."""

    def __init__(self, *, little_endian: bool = False) -> None:
        kernel = encode_kernel_le if little_endian else encode_kernel
        super().__init__(kernel, np.zeros(2, np.int64), np.uint32, max_channel=0x1F)


def encode_evt21(
    events: EventArray, triggers: TriggerEvents | None = None, *, little_endian: bool = False
) -> bytes:
    """One-shot EVT 2.1 encoding of a whole recording."""
    return Evt21Encoder(little_endian=little_endian).encode(events, triggers)
