"""Bayer mosaic <-> RGB (rigd.core.pixels): which OpenCV code restores an RGGB mosaic, and how
close the demosaic comes on flat colour regions."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from rigd.core.errors import TakeFormatError
from rigd.core.pixels import demosaic, demosaic_gray, mosaic_rggb, stored_pixel_format, to_gray, to_rgb

#: Flat patches of known, distinct colours (RGB), one per 40x40 tile.
COLOURS = np.array(
    [[220, 30, 10], [20, 200, 40], [15, 25, 230], [250, 160, 0], [128, 128, 128], [90, 10, 180]], np.uint8
)


def _patches(tile: int = 40) -> np.ndarray:
    img = np.zeros((2 * tile, 3 * tile, 3), np.uint8)
    for k, c in enumerate(COLOURS):
        r, q = divmod(k, 3)
        img[r * tile : (r + 1) * tile, q * tile : (q + 1) * tile] = c
    return img


def _interiors(img: np.ndarray, tile: int = 40, margin: int = 4) -> list[np.ndarray]:
    out = []
    for k in range(len(COLOURS)):
        r, q = divmod(k, 3)
        out.append(
            img[r * tile + margin : (r + 1) * tile - margin, q * tile + margin : (q + 1) * tile - margin]
        )
    return out


def test_mosaic_takes_each_sites_channel() -> None:
    rgb = np.random.default_rng(0).integers(0, 256, (6, 8, 3), dtype=np.uint8)
    m = mosaic_rggb(rgb)
    assert m.shape == (6, 8)
    assert m.dtype == np.uint8
    assert np.array_equal(m[0::2, 0::2], rgb[0::2, 0::2, 0])  # R at (even, even)
    assert np.array_equal(m[0::2, 1::2], rgb[0::2, 1::2, 1])  # G at (0, 1)
    assert np.array_equal(m[1::2, 0::2], rgb[1::2, 0::2, 1])  # G at (1, 0)
    assert np.array_equal(m[1::2, 1::2], rgb[1::2, 1::2, 2])  # B at (1, 1)


def test_roundtrip_restores_flat_colours() -> None:
    img = _patches()
    back = demosaic(mosaic_rggb(img))
    assert back.shape == img.shape
    assert back.dtype == np.uint8
    for colour, region in zip(COLOURS, _interiors(back), strict=True):
        err = np.abs(region.astype(np.int16) - colour.astype(np.int16)).max()
        assert err <= 1, (colour, err)


def test_opencv_names_rggb_bayerbg() -> None:
    """The offset this module works around: OpenCV's BayerRG code swaps red and blue of an
    RGGB mosaic; BayerBG (what demosaic uses) restores them."""
    m = mosaic_rggb(_patches())
    red = _interiors(np.asarray(cv2.cvtColor(m, cv2.COLOR_BayerRG2RGB)))[0]
    assert red[..., 2].mean() > 200
    assert red[..., 0].mean() < 20
    assert np.array_equal(demosaic(m), cv2.cvtColor(m, cv2.COLOR_BayerBG2RGB_EA))


def test_gray_matches_the_rgb_luminance_on_flat_regions() -> None:
    img = _patches()
    gray = demosaic_gray(mosaic_rggb(img))
    want = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    for got, ref in zip(_interiors(gray), _interiors(want), strict=True):
        assert np.abs(got.astype(np.int16) - ref.astype(np.int16)).max() <= 2
    assert np.array_equal(to_gray(mosaic_rggb(img), "bayer_rg8"), gray)


def test_to_rgb_leaves_mono_and_rgb_alone() -> None:
    mono = np.zeros((4, 4), np.uint8)
    rgb = np.zeros((4, 4, 3), np.uint8)
    assert to_rgb(mono, "mono8") is mono
    assert to_rgb(rgb, "rgb8") is rgb
    assert to_rgb(mono, None) is mono
    assert to_rgb(mono, "bayer_rg8").shape == (4, 4, 3)


def test_demosaic_refuses_what_is_no_mosaic() -> None:
    with pytest.raises(ValueError, match="uint8"):
        demosaic(np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(ValueError, match="GRBG"):
        demosaic(np.zeros((4, 4), np.uint8), "GRBG")


def test_stored_pixel_format() -> None:
    assert stored_pixel_format({}, (4, 4, 3), "x") == "rgb8"
    assert stored_pixel_format({}, (4, 4), "x") == "mono8"  # older takes: by the shape
    assert (
        stored_pixel_format({"pixel_format": "bayer_rg8", "bayer_pattern": "RGGB"}, (4, 4), "x")
        == "bayer_rg8"
    )
    with pytest.raises(TakeFormatError, match=r"/frames/cam0.*does not fit"):
        stored_pixel_format({"pixel_format": "bayer_rg8", "bayer_pattern": "RGGB"}, (4, 4, 3), "/frames/cam0")
    with pytest.raises(TakeFormatError, match="bayer_pattern 'BGGR'"):
        stored_pixel_format({"pixel_format": "bayer_rg8", "bayer_pattern": "BGGR"}, (4, 4), "x")
    with pytest.raises(TakeFormatError, match="'yuv422'"):
        stored_pixel_format({"pixel_format": "yuv422"}, (4, 4), "x")
