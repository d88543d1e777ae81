"""PanopticSports layout: Dynamic3DGaussians' `train.py` and 4DGaussians' PanopticSports reader.

    train_meta.json, test_meta.json  {w, h, k[t][c], w2c[t][c], fn[t][c], cam_id[t][c]} plus
                                     t_us[t][c] (mid-exposure, rig us), time[t][c] in [0, 1],
                                     timestep[t], cam_name[t][c]
    ims/<c>/<t:06d>.jpg              undistorted frames (RGB JPEG)
    seg/<c>/<t:06d>.png              dynamic3dgs: all-foreground masks (value 1)
    init_pt_cld.npz                  data: (N, 7) float64 xyz (m), rgb in [0, 1], seg (1)

Both trainers render with diff-gaussian-rasterization, whose projection (`setup_camera`: NDC
from cx, then ((ndc + 1) w - 1) / 2) puts pixel (0, 0)'s centre at 0.5: `k` holds rigd's
principal point + 0.5. Dynamic3DGaussians trains every entry of `fn` in order, one timestep
each, initialising timestep t from t - 1, and 4DGaussians gives entry t the time t / len(fn) in
either meta: so both metas hold every timestep and the split is by camera by default (the
PanopticSports way); `--split time` puts the even timesteps in train and the odd in test.
Dynamic3DGaussians' `get_dataset` opens `seg/<fn>.png` for every image, so dynamic3dgs writes
all-foreground masks (rigd has no segmentation: they let it load, they separate nothing).
`cam_id` is the camera's position in the rig (0, 1, 2, ...).
"""

from __future__ import annotations

import json
import logging

import numpy as np

from rigd.core.errors import ConfigError
from rigd.products.export.common import PIXEL_CENTRE, ExportPlan, K_at
from rigd.products.export.outputs import write_image
from rigd.products.export.points import cloud_of

log = logging.getLogger(__name__)


def fn(k: int, j: int) -> str:
    """Path of timestep k, camera j under ims/ (the meta's `fn` entry)."""
    return f"{j}/{k:06d}.jpg"


def write(plan: ExportPlan) -> None:
    cams, fr = plan.cameras, plan.frames
    fmt = plan.options.format
    if len({c.size for c in cams}) != 1:
        sizes = {c.name: c.size for c in cams}
        raise ConfigError(f"{fmt} needs one image size for every camera ({sizes}): pass --resize WxH")
    plan.write_images(lambda k, j: f"ims/{fn(k, j)}")
    if fmt == "dynamic3dgs":
        for k in range(fr.pulses.size):
            for j, c in enumerate(cams):
                dest = plan.out / "seg" / fn(k, j).replace(".jpg", ".png")
                dest.parent.mkdir(parents=True, exist_ok=True)
                write_image(dest, np.ones((c.size[1], c.size[0]), np.uint8))
    time01 = fr.time01()
    w, h = cams[0].size
    ks = [K_at(c.K, PIXEL_CENTRE["gaussians"]).tolist() for c in cams]
    train = plan.train_mask
    for split, mask in (("train", train), ("test", ~train)):
        steps = [int(k) for k in np.flatnonzero(mask.any(axis=1))]
        views = [[int(j) for j in np.flatnonzero(mask[k])] for k in steps]
        meta = {
            "w": w,
            "h": h,
            "k": [[ks[j] for j in js] for js in views],
            "w2c": [[cams[j].w2c.tolist() for j in js] for js in views],
            "fn": [[fn(k, j) for j in js] for k, js in zip(steps, views, strict=True)],
            "cam_id": views,
            "cam_name": [[cams[j].name for j in js] for js in views],
            "t_us": [[int(fr.t_us[k, j]) for j in js] for k, js in zip(steps, views, strict=True)],
            "time": [[float(time01[k, j]) for j in js] for k, js in zip(steps, views, strict=True)],
            "timestep": steps,
            "world": plan.world_note,
        }
        (plan.out / f"{split}_meta.json").write_text(json.dumps(meta))
    cloud = cloud_of(plan)
    data = np.c_[cloud.xyz, cloud.rgb / 255.0, np.ones(len(cloud))]
    np.savez_compressed(plan.out / "init_pt_cld.npz", data=data)
    log.info("%s: %d timesteps x %d cameras, %d points", fmt, fr.pulses.size, len(cams), len(cloud))
