"""Regenerate the README's pictures of what rigd produces, from the simulated rig:

- `inspect-thumbnails.png`: the contact sheet `rigd inspect TAKE --thumbnails` writes;
- `calibration-rig.png`: the camera-frusta figure the `rigd calibrate rig --report` HTML embeds.

Run from the repository root with rigd installed: `python docs/img/make_images.py`. The take runs on
virtual time, so the pictures are the same on every machine. Each image is scaled down to stay
small in the repository (under 300 KB).
"""

from __future__ import annotations

import base64
import logging
import re
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from rigd.app.capture import run_capture
from rigd.app.config import RigConfig, default_sim_rig
from rigd.products.calibrate import RigOptions, TakeSource, run_rig
from rigd.products.inspect import write_thumbnails

log = logging.getLogger("make_images")

HERE = Path(__file__).resolve().parent
#: The sim's moving board (firmware_sim.board_scene.BoardScene's default board).
BOARD = "chessboard:9x6:0.08"
#: Width the pictures are scaled down to.
MAX_WIDTH = 1200
MAX_BYTES = 300_000


def board_rig() -> RigConfig:
    """The built-in sim rig (three cameras, two event sensors) watching the moving board."""
    cfg = default_sim_rig(world="docs-images", resolution=(640, 360), pixel_format="mono8", clock="virtual")
    data = cfg.model_dump()
    for dev in [*data["cameras"], *data["event_sensors"]]:
        dev["spec"] += "&scene=board"
    return RigConfig.model_validate(data)


def save(img: np.ndarray, name: str) -> Path:
    """Scale `img` down to MAX_WIDTH and write it as a compressed PNG beside this script."""
    if img.shape[1] > MAX_WIDTH:
        scale = MAX_WIDTH / img.shape[1]
        img = cv2.resize(img, (MAX_WIDTH, round(img.shape[0] * scale)), interpolation=cv2.INTER_AREA)
    path = HERE / name
    if not cv2.imwrite(str(path), img, [cv2.IMWRITE_PNG_COMPRESSION, 9]):
        raise OSError(f"could not write {path}")
    size = path.stat().st_size
    if size > MAX_BYTES:
        raise SystemExit(f"{path}: {size} bytes, over the {MAX_BYTES} kept in the repository")
    log.info("wrote %s (%dx%d, %d KB)", path, img.shape[1], img.shape[0], size // 1000)
    return path


def embedded_png(html: str, alt_prefix: str) -> np.ndarray:
    """The figure of the report whose alt text starts with `alt_prefix`, decoded."""
    found = re.search(r'<img src="data:image/png;base64,([^"]+)" alt="' + re.escape(alt_prefix), html)
    if found is None:
        raise SystemExit(f"the report has no figure {alt_prefix!r}")
    data = np.frombuffer(base64.b64decode(found.group(1)), np.uint8)
    return np.asarray(cv2.imdecode(data, cv2.IMREAD_COLOR), np.uint8)


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    with tempfile.TemporaryDirectory(prefix="rigd-docs-") as tmp:
        work = Path(tmp)
        take = run_capture(board_rig(), work, 2.0).path
        sheet = write_thumbnails(take, work / "sheet.png", n_frames=4)
        save(np.asarray(cv2.imread(str(sheet)), np.uint8), "inspect-thumbnails.png")
        report = work / "report.html"
        run_rig(RigOptions(board=BOARD, source=TakeSource(path=take), out=work / "rig.yaml", report=report))
        save(embedded_png(report.read_text(), "camera frusta"), "calibration-rig.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
