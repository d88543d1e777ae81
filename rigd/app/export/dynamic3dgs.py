"""Dynamic3DGaussians (PanopticSports) layout.

    train_meta.json, test_meta.json  {w, h, k[t][c], w2c[t][c], fn[t][c], cam_id[t][c]} plus
                                     t_us[t][c] (mid-exposure, rig us) and time[t][c] in [0, 1]
    ims/<c>/<t:06d>.jpg              undistorted frames (RGB JPEG)
    init_pt_cld.npz                  data: (N, 7) float64 xyz (m), rgb in [0, 1], seg (1)

Dynamic3DGaussians trains on every entry of a meta file in timestep order, one timestep per
entry of `fn`; here the train meta holds the even timesteps and the test meta the odd ones
(the paper's 15-of-30 FPS split). `cam_id` is the camera's position in the rig (0, 1, 2, ...).
Its train.py also opens `seg/<fn>.png`; no segmentation is known, so `seg/` is only written on
request (`--seg`: every pixel foreground, value 1), and every point of the cloud has seg = 1.
"""

from __future__ import annotations

import json
import logging

import numpy as np

from rigd.app.export.common import ExportPlan
from rigd.app.export.outputs import write_image
from rigd.app.export.points import triangulate
from rigd.core.errors import ConfigError

log = logging.getLogger(__name__)


def fn(k: int, j: int) -> str:
    """Path of timestep k, camera j under ims/ (the meta's `fn` entry)."""
    return f"{j}/{k:06d}.jpg"


def write(plan: ExportPlan) -> None:
    cams, fr = plan.cameras, plan.frames
    if len({c.size for c in cams}) != 1:
        sizes = {c.name: c.size for c in cams}
        raise ConfigError(f"dynamic3dgs needs one image size for every camera ({sizes}): pass --resize WxH")
    seg = plan.options.seg
    plan.write_images(lambda k, j: f"ims/{fn(k, j)}")
    if seg:
        for k in range(fr.pulses.size):
            for j, c in enumerate(cams):
                dest = plan.out / "seg" / fn(k, j).replace(".jpg", ".png")
                dest.parent.mkdir(parents=True, exist_ok=True)
                write_image(dest, np.ones((c.size[1], c.size[0]), np.uint8))
    time01 = fr.time01()
    w, h = cams[0].size
    for split, mask in (("train", fr.train), ("test", ~fr.train)):
        ks = np.flatnonzero(mask)
        meta = {
            "w": w,
            "h": h,
            "k": [[c.K.tolist() for c in cams] for _ in ks],
            "w2c": [[c.w2c.tolist() for c in cams] for _ in ks],
            "fn": [[fn(int(k), j) for j in range(len(cams))] for k in ks],
            "cam_id": [list(range(len(cams))) for _ in ks],
            "cam_name": [c.name for c in cams],
            "t_us": [[int(v) for v in fr.t_us[k]] for k in ks],
            "time": [[float(v) for v in time01[k]] for k in ks],
            "timestep": [int(k) for k in ks],
        }
        (plan.out / f"{split}_meta.json").write_text(json.dumps(meta))
    cloud = triangulate(plan)
    data = np.c_[cloud.xyz, cloud.rgb / 255.0, np.ones(len(cloud))]
    np.savez_compressed(plan.out / "init_pt_cld.npz", data=data)
    log.info("dynamic3dgs: %d timesteps x %d cameras, %d points", fr.pulses.size, len(cams), len(cloud))
