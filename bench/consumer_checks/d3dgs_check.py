"""Dynamic3DGaussians (train.py at the pinned commit, unmodified) on rigd's dynamic3dgs export:
`get_dataset` for every timestep of train_meta.json (no --seg flag), `initialize_params`, the
floor loss of its `get_loss` on the initial points, and the board projected by its cameras.

usage: python d3dgs_check.py D3DGS_REPO EXPORT_DIR VIEWS_JSON
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import cuda_stubs
import torch


def main() -> None:
    repo, export, views = Path(sys.argv[1]), Path(sys.argv[2]).resolve(), Path(sys.argv[3])
    cuda_stubs.install()
    sys.path.insert(0, str(repo))
    import train  # Dynamic3DGaussians' train.py

    work = Path(os.environ.get("CHECK_WORK", "."))
    (work / "data").mkdir(exist_ok=True)
    seq = "rigd"
    link = work / "data" / seq
    if link.is_symlink() or link.exists():
        link.unlink()
    link.symlink_to(export)
    os.chdir(work)  # it reads ./data/<seq>/...
    cams = {}
    for split in ("train", "test"):
        md = json.loads(Path(f"./data/{seq}/{split}_meta.json").read_text())
        for t in range(len(md["fn"])):
            data = train.get_dataset(t, md, seq)
            assert len(data) == len(md["fn"][t])
            for c, d in enumerate(data):
                cams[md["fn"][t][c]] = d["cam"]
        images = sum(len(f) for f in md["fn"])
        print(f"  {split}_meta.json: get_dataset loaded all {len(md['fn'])} timesteps ({images} images)")
    md = json.loads(Path(f"./data/{seq}/train_meta.json").read_text())
    params, _ = train.initialize_params(seq, md)
    fg = params["means3D"][params["seg_colors"][:, 0] > 0.5]
    floor = float(torch.clamp(fg[:, 1].detach(), min=0).mean())
    print(f"  initialize_params: {len(params['means3D'])} points; its floor loss on them {floor:.6f}")
    assert floor == 0.0, floor
    print("  " + cuda_stubs.check_views(cams, json.loads(views.read_text())))


if __name__ == "__main__":
    main()
