"""Pixel formats of camera frames, and the Bayer mosaic <-> RGB conversions between them.

A `bayer_rg8` camera sends its raw colour-filter mosaic, one byte per pixel: a third of rgb8's
bandwidth and disk. Takes store it as sent (the writer never converts while recording) and every
reader that shows or uses images demosaics it on read (`to_rgb`, `to_gray`).

OpenCV names a Bayer pattern by the 2x2 block starting at (1, 1), not at (0, 0) as sensor data
sheets (and GenICam's `BayerRG8`) do: a sensor's RGGB mosaic is OpenCV's `BayerBG`. The codes
below are the ones `tests/rigd/test_pixels.py` verifies against an image of known colours.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Final, Literal

import numpy as np
from numpy.typing import NDArray

from rigd.core.errors import TakeFormatError
from rigd.core.extras import require
from rigd.core.layout import Frames

PixelFormat = Literal["mono8", "rgb8", "bayer_rg8"]
#: Every pixel format a camera may be set to.
PIXEL_FORMATS: Final = ("mono8", "rgb8", "bayer_rg8")
#: Colour-filter layout of each Bayer format, sensor naming: R at (even row, even column).
BAYER_PATTERNS: Final = {"bayer_rg8": "RGGB"}
#: Bytes one pixel takes on the wire and in a take.
BYTES_PER_PIXEL: Final = {"mono8": 1, "rgb8": 3, "bayer_rg8": 1}

# OpenCV's name for the sensor's RGGB is BayerBG (see the module docstring). The edge-aware
# variant: as fast as the bilinear one (bench.bayer_frames), with less zipper on sharp edges
# (99th percentile error on the sim's board 1 DN against 5; docs/decisions/0016). OpenCV is
# imported on first use: a lean install (`pip install rigd`) reads every array of a take,
# Bayer mosaics as stored, and asks for the `frames` extra only to demosaic.
_TO_RGB: Final = {"RGGB": "COLOR_BayerBG2RGB_EA"}


def _cv2() -> Any:
    return require("cv2", "demosaicing Bayer frames or converting RGB to gray")


U8 = NDArray[np.uint8]


def is_bayer(pixel_format: str | None) -> bool:
    return pixel_format in BAYER_PATTERNS


def frame_shape(height: int, width: int, pixel_format: str) -> tuple[int, ...]:
    """The (H, W) or (H, W, 3) array a camera in this format delivers."""
    return (height, width, 3) if pixel_format == "rgb8" else (height, width)


def mosaic_rggb(rgb: NDArray[np.uint8]) -> U8:
    """The RGGB mosaic a Bayer sensor would record of an (H, W, 3) RGB image: R at (0, 0),
    G at (0, 1) and (1, 0), B at (1, 1) of every 2x2 block."""
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"mosaic_rggb needs an (H, W, 3) RGB image, got shape {rgb.shape}")
    out = np.empty(rgb.shape[:2], dtype=rgb.dtype)
    out[0::2, 0::2] = rgb[0::2, 0::2, 0]
    out[0::2, 1::2] = rgb[0::2, 1::2, 1]
    out[1::2, 0::2] = rgb[1::2, 0::2, 1]
    out[1::2, 1::2] = rgb[1::2, 1::2, 2]
    return out


def _check_mosaic(mosaic: NDArray[Any], pattern: str) -> None:
    if pattern not in _TO_RGB:
        raise ValueError(f"Bayer pattern {pattern!r} is not supported (known: {sorted(_TO_RGB)})")
    if mosaic.ndim != 2 or mosaic.dtype != np.uint8:
        raise ValueError(f"a Bayer mosaic is (H, W) uint8, got shape {mosaic.shape} {mosaic.dtype}")


def demosaic(mosaic: NDArray[Any], pattern: str = "RGGB") -> U8:
    """(H, W, 3) RGB of a Bayer mosaic (OpenCV's edge-aware demosaic: ~1 ms per 720p frame)."""
    _check_mosaic(mosaic, pattern)
    cv2 = _cv2()
    return np.asarray(
        cv2.cvtColor(np.ascontiguousarray(mosaic), getattr(cv2, _TO_RGB[pattern])), dtype=np.uint8
    )


def demosaic_gray(mosaic: NDArray[Any], pattern: str = "RGGB") -> U8:
    """(H, W) luminance of a Bayer mosaic, what a board detector needs: the gray of the
    demosaiced RGB (OpenCV's direct Bayer-to-gray is bilinear, with its zipper on edges)."""
    cv2 = _cv2()
    return np.asarray(cv2.cvtColor(demosaic(mosaic, pattern), cv2.COLOR_RGB2GRAY), dtype=np.uint8)


def to_rgb(image: NDArray[Any], pixel_format: str | None) -> NDArray[Any]:
    """A frame as it is viewed: Bayer mosaics demosaiced to (H, W, 3) RGB; mono and RGB frames
    are returned as they are."""
    if pixel_format is not None and is_bayer(pixel_format):
        return demosaic(image, BAYER_PATTERNS[pixel_format])
    return image


def to_gray(image: NDArray[Any], pixel_format: str | None) -> NDArray[Any]:
    """A frame as (H, W) gray: Bayer mosaics demosaiced, RGB converted, mono as it is."""
    if pixel_format is not None and is_bayer(pixel_format):
        return demosaic_gray(image, BAYER_PATTERNS[pixel_format])
    if image.ndim == 3 and image.shape[2] == 3:
        cv2 = _cv2()
        return np.asarray(cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY))
    return image


def stored_pixel_format(attrs: Mapping[str, Any], shape: tuple[int, ...], where: str) -> str:
    """The pixel format of a take's `/frames/<camera>` group: its `pixel_format` attr, or for
    takes written before it existed rgb8 / mono8 by the frame shape. TakeFormatError naming `where`
    for an attr that contradicts the shape or names an unknown format."""
    raw = attrs.get(Frames.PIXEL_FORMAT)
    by_shape = "rgb8" if len(shape) == 3 else "mono8"
    if raw is None:
        return by_shape
    fmt = raw.decode() if isinstance(raw, bytes) else str(raw)
    if fmt not in PIXEL_FORMATS:
        raise TakeFormatError(f"{where}: pixel_format {fmt!r} is not one of {', '.join(PIXEL_FORMATS)}")
    if len(frame_shape(1, 1, fmt)) != len(shape):
        raise TakeFormatError(f"{where}: pixel_format {fmt!r} does not fit frames of shape {shape}")
    if is_bayer(fmt):
        pattern = attrs.get(Frames.BAYER_PATTERN)
        pattern = pattern.decode() if isinstance(pattern, bytes) else pattern
        if pattern != BAYER_PATTERNS[fmt]:
            raise TakeFormatError(
                f"{where}: pixel_format {fmt!r} with bayer_pattern {pattern!r} "
                f"(expected {BAYER_PATTERNS[fmt]!r})"
            )
    return fmt
