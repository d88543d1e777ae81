"""Prophesee EVT 2.0 / 2.1 / 3.0 codec, RAW and DAT files (numba kernels, OpenEB semantics).

Imports only numpy, numba and rigd.core, so the daemon, the simulator and the tools share one
decoder and one encoder.
"""

from rigd.evt.dat import DatHeader, read_dat, write_dat
from rigd.evt.errors import KIND_NAMES, EvtDecodeError
from rigd.evt.evt2 import Evt2Encoder, encode_evt2
from rigd.evt.evt3 import Evt3Encoder, encode_evt3
from rigd.evt.evt21 import Evt21Encoder, encode_evt21
from rigd.evt.jumps import TimeJump
from rigd.evt.kernels import JUMP_CONFIRM
from rigd.evt.raw import (
    FORMATS,
    Decoded,
    Scanned,
    StreamDecoder,
    decode_bytes,
    decode_chunk,
    decode_from_state,
)
from rigd.evt.raw_file import RawReader, encode, read_raw, warm_up_decoder, write_raw
from rigd.evt.raw_header import RawHeader, parse_raw_header

__all__ = [
    "FORMATS",
    "JUMP_CONFIRM",
    "KIND_NAMES",
    "DatHeader",
    "Decoded",
    "Evt2Encoder",
    "Evt3Encoder",
    "Evt21Encoder",
    "EvtDecodeError",
    "RawHeader",
    "RawReader",
    "Scanned",
    "StreamDecoder",
    "TimeJump",
    "decode_bytes",
    "decode_chunk",
    "decode_from_state",
    "encode",
    "encode_evt2",
    "encode_evt3",
    "encode_evt21",
    "parse_raw_header",
    "read_dat",
    "read_raw",
    "warm_up_decoder",
    "write_dat",
    "write_raw",
]
