"""nerfstudio `transforms.json` plus D-NeRF style `transforms_train.json` / `transforms_test.json`.

    transforms.json        camera_model PINHOLE, per frame fl_x fl_y cx cy w h, file_path,
                           transform_matrix (camera -> world, OpenGL axes: x right, y up, z back),
                           time in [0, 1], t_us (mid-exposure, rig us), camera, timestep, split;
                           train_filenames / test_filenames for nerfstudio's split lists
    transforms_train.json  D-NeRF: camera_angle_x (of the first camera), frames with file_path
    transforms_test.json   WITHOUT extension (the D-NeRF loader appends .png), time, transform_matrix,
                           and the same per-frame intrinsics
    images/<cam>/<t:06d>.png

Images are undistorted, so the model is PINHOLE with the new K (principal point at the image
centre when the lens had distortion, which D-NeRF's centred-pinhole assumption needs).
"""

from __future__ import annotations

import json
import logging
import math
from typing import Any

import numpy as np

from rigd.app.export.common import ExportPlan

log = logging.getLogger(__name__)


def image_path(plan: ExportPlan, k: int, j: int) -> str:
    return f"images/{plan.cameras[j].name}/{k:06d}.png"


def write(plan: ExportPlan) -> None:
    cams, fr = plan.cameras, plan.frames
    plan.write_images(lambda k, j: image_path(plan, k, j))
    time01 = fr.time01()
    frames: list[dict[str, Any]] = []
    for k in range(fr.pulses.size):
        for j, c in enumerate(cams):
            frames.append(
                {
                    "file_path": image_path(plan, k, j),
                    "transform_matrix": c.c2w_gl.tolist(),
                    "fl_x": float(c.K[0, 0]),
                    "fl_y": float(c.K[1, 1]),
                    "cx": float(c.K[0, 2]),
                    "cy": float(c.K[1, 2]),
                    "w": c.size[0],
                    "h": c.size[1],
                    "time": float(time01[k, j]),
                    "t_us": int(fr.t_us[k, j]),
                    "camera": c.name,
                    "timestep": k,
                    "split": "train" if fr.train[k] else "test",
                }
            )
    top = {
        "camera_model": "PINHOLE",
        "frames": frames,
        "train_filenames": [f["file_path"] for f in frames if f["split"] == "train"],
        "test_filenames": [f["file_path"] for f in frames if f["split"] == "test"],
        "t0_us": fr.t0_us,
        "t1_us": fr.t1_us,
    }
    (plan.out / "transforms.json").write_text(json.dumps(top, indent=1))
    fx, w = float(cams[0].K[0, 0]), cams[0].size[0]
    for split in ("train", "test"):
        dnerf = [
            {**f, "file_path": "./" + f["file_path"].removesuffix(".png"), "rotation": 0.0}
            for f in frames
            if f["split"] == split
        ]
        meta = {"camera_angle_x": 2 * math.atan(w / (2 * fx)), "frames": dnerf}
        (plan.out / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1))
    log.info("nerfstudio: %d frames (%d train)", len(frames), int(np.count_nonzero(fr.train)) * len(cams))
