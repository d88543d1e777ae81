"""nerfstudio `transforms.json` plus D-NeRF style `transforms_{train,val,test}.json`.

    transforms.json        camera_model PINHOLE, per frame fl_x fl_y cx cy w h (nerfstudio's pixel
                           convention: pixel centres at +0.5, so cx is rigd's + 0.5), file_path with
                           its extension, transform_matrix (camera -> world, OpenGL axes: x right,
                           y up, z back), time in [0, 1], t_us (mid-exposure, rig us), camera,
                           timestep, split; train_filenames / val_filenames / test_filenames
                           (nerfstudio asks for the list of every split once one is given; val is
                           the held-out set); ply_file_path: the initial points (sparse_pc.ply)
    transforms_{train,val,test}.json  D-NeRF: camera_angle_x (of the first camera), frames with
                           file_path WITHOUT extension (its loader appends .png), time,
                           transform_matrix, and the same per-frame intrinsics
    images/<cam>/<t:06d>.png
    sparse_pc.ply          the triangulated initial points in the export's world

nerfstudio's own `nerfstudio-data` parser ignores `time`; its `dnerf` parser reads it but knows
one focal length and a centred principal point (`camera_angle_x`): a warning says when the
cameras differ from that.
"""

from __future__ import annotations

import json
import logging
import math
from typing import Any

import numpy as np

from rigd.products.export.common import PIXEL_CENTRE, ExportPlan, K_at
from rigd.products.export.points import cloud_of, write_ply

log = logging.getLogger(__name__)

PLY = "sparse_pc.ply"


def image_path(plan: ExportPlan, k: int, j: int) -> str:
    return f"images/{plan.cameras[j].name}/{k:06d}.png"


#: A camera D-NeRF's model misdescribes by more than this (px) is warned about; up to it (the
#: simulator's cx = w/2 is half a pixel off centre) it is logged at INFO.
DNERF_WARN_PX = 0.51


def _dnerf_mismatch(plan: ExportPlan) -> list[tuple[str, float]]:
    """(camera, px) for the cameras that D-NeRF's one-focal, centred-pinhole model misdescribes
    by over 0.01 px: the larger of the principal point's distance from the centre and the focal
    lengths' difference from camera 0's (scaled to the image width) and from each other."""
    c0 = plan.cameras[0]
    bad = []
    for c in plan.cameras:
        K = K_at(c.K, PIXEL_CENTRE["nerfstudio"])  # noqa: N806
        off = max(abs(K[0, 2] - c.size[0] / 2), abs(K[1, 2] - c.size[1] / 2))
        focal = max(abs(K[0, 0] - c0.K[0, 0] * c.size[0] / c0.size[0]), abs(K[1, 1] - K[0, 0]))
        if max(off, focal) > 0.01:
            bad.append((c.name, float(max(off, focal))))
    return bad


def write(plan: ExportPlan) -> None:
    cams, fr = plan.cameras, plan.frames
    plan.write_images(lambda k, j: image_path(plan, k, j))
    cloud = cloud_of(plan)
    write_ply(cloud, plan.out / PLY)
    time01 = fr.time01()
    train = plan.train_mask
    frames: list[dict[str, Any]] = []
    for k in range(fr.pulses.size):
        for j, c in enumerate(cams):
            K = K_at(c.K, PIXEL_CENTRE["nerfstudio"])  # noqa: N806
            frames.append(
                {
                    "file_path": image_path(plan, k, j),
                    "transform_matrix": c.c2w_gl.tolist(),
                    "fl_x": float(K[0, 0]),
                    "fl_y": float(K[1, 1]),
                    "cx": float(K[0, 2]),
                    "cy": float(K[1, 2]),
                    "w": c.size[0],
                    "h": c.size[1],
                    "time": float(time01[k, j]),
                    "t_us": int(fr.t_us[k, j]),
                    "camera": c.name,
                    "timestep": k,
                    "split": "train" if train[k, j] else "test",
                }
            )
    held_out = [f["file_path"] for f in frames if f["split"] == "test"]
    top = {
        "camera_model": "PINHOLE",
        "frames": frames,
        "train_filenames": [f["file_path"] for f in frames if f["split"] == "train"],
        "val_filenames": held_out,
        "test_filenames": held_out,
        "ply_file_path": PLY,
        "t0_us": fr.t0_us,
        "t1_us": fr.t1_us,
        "world": plan.world_note,
        "pixel_centre": "nerfstudio's: pixel (0, 0) is centred at (0.5, 0.5)",
    }
    (plan.out / "transforms.json").write_text(json.dumps(top, indent=1))
    bad = _dnerf_mismatch(plan)
    if bad:
        worst = max(px for _, px in bad)
        log.log(
            logging.WARNING if worst > DNERF_WARN_PX else logging.INFO,
            "transforms_*.json (D-NeRF) describe every camera with one focal length and a centred "
            "principal point, which is off by up to %.2f px for %s: use transforms.json (per-frame "
            "intrinsics)",
            worst,
            ", ".join(f"{name} ({px:.2f} px)" for name, px in bad),
        )
    fx, w = float(cams[0].K[0, 0]), cams[0].size[0]
    for split, kind in (("train", "train"), ("val", "test"), ("test", "test")):
        dnerf = [
            {**f, "file_path": "./" + f["file_path"].removesuffix(".png"), "rotation": 0.0}
            for f in frames
            if f["split"] == kind
        ]
        meta = {"camera_angle_x": 2 * math.atan(w / (2 * fx)), "frames": dnerf}
        (plan.out / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1))
    log.info("nerfstudio: %d frames (%d train)", len(frames), int(np.count_nonzero(train)))
