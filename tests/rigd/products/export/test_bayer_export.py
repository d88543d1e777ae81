"""`rigd export` of a bayer_rg8 take: every layout writes viewable RGB images, the same (within
the demosaic's error) as the export of an rgb8 take of the same virtual-clock scene."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from firmware_sim.scene import Scene
from firmware_sim.world import get_world, reset_world
from rigd.app.capture import run_capture
from rigd.app.config import default_sim_rig
from rigd.products.export import FORMATS, ExportOptions, run_export
from rigd.products.export.common import UNCALIBRATED_FORMATS
from rigd.take.calibration import store_calibration
from rigd.take.reader import open_take

#: The layouts that write images (mcap keeps the mosaics as stored: tests/rigd/products/ros).
LAYOUTS = [f for f in FORMATS if f not in UNCALIBRATED_FORMATS]

pytestmark = pytest.mark.slow

RES = (320, 180)


def _capture(root: Path, fmt: str) -> Path:
    """A coloured (sprites) scene: a Bayer export that swapped red and blue would show."""
    world = f"t-export-{fmt}"
    reset_world(world)
    cfg = default_sim_rig(world=world, resolution=RES, pixel_format=fmt, clock="virtual")  # type: ignore[arg-type]
    path = run_capture(cfg, root / fmt, 0.5).path
    scene = get_world(world).resource("scene", Scene)
    assert isinstance(scene, Scene)
    with open_take(path) as tk:
        devices = tk.cameras + tk.event_sensors
    for d in devices:
        K, R, t = scene.view_camera(d, *RES)  # noqa: N806
        intr = {"K": K.tolist(), "dist": [0.0] * 5, "image_size": list(RES)}
        store_calibration(path, d, intr, {"R": R.tolist(), "t": t.tolist()}, source="sim ground truth")
    reset_world(world)
    return path


@pytest.fixture(scope="module")
def exports(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, Path]]:
    root = tmp_path_factory.mktemp("bayer-export")
    out: dict[str, dict[str, Path]] = {}
    for pf in ("rgb8", "bayer_rg8"):
        take = _capture(root, pf)
        out[pf] = {}
        for fmt in LAYOUTS:
            out[pf][fmt] = root / f"{pf}-{fmt}"
            run_export(ExportOptions(take=take, format=fmt, out=out[pf][fmt]))
    return out


def _images(root: Path) -> list[Path]:
    """The exported camera images (not dynamic3dgs' all-foreground `seg/` masks)."""
    return sorted(
        p
        for p in root.rglob("*")
        if p.suffix.lower() in (".png", ".jpg", ".jpeg") and "seg" not in p.relative_to(root).parts
    )


@pytest.mark.parametrize(
    "fmt", [f for f in FORMATS if f not in UNCALIBRATED_FORMATS]
)  # mcap: mosaics as stored
def test_every_layout_writes_rgb_like_the_rgb8_take(exports: dict[str, dict[str, Path]], fmt: str) -> None:
    ref, bayer = _images(exports["rgb8"][fmt]), _images(exports["bayer_rg8"][fmt])
    assert [p.relative_to(exports["rgb8"][fmt]) for p in ref] == [
        p.relative_to(exports["bayer_rg8"][fmt]) for p in bayer
    ]
    assert len(bayer) >= 3 * 10
    errors, swapped = [], []
    for a_path, b_path in zip(ref, bayer, strict=True):
        a, b = cv2.imread(str(a_path), cv2.IMREAD_UNCHANGED), cv2.imread(str(b_path), cv2.IMREAD_UNCHANGED)
        assert b.ndim == 3
        assert b.shape == a.shape
        # Colour, not a mosaic copied into three channels:
        assert np.abs(b.astype(np.int16) - b[..., ::-1].astype(np.int16)).mean() > 3
        errors.append(np.abs(a.astype(np.int16) - b.astype(np.int16)).mean())
        swapped.append(np.abs(a.astype(np.int16) - b[..., ::-1].astype(np.int16)).mean())
    # Measured (320x180, mean |error| per image, edge-aware demosaic): 1.3-1.5 DN for the PNG
    # layouts, 2.0-2.2 DN for the JPEG ones; red and blue swapped: about 15 DN.
    print(f"{fmt}: mean |error| {min(errors):.2f}..{max(errors):.2f} DN, swapped {min(swapped):.2f}..")
    assert max(errors) < 4.0, errors
    assert min(swapped) > 2 * max(errors), (errors, swapped)
