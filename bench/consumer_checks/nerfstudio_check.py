"""nerfstudio's own dataparsers (installed from the registry) on rigd's nerfstudio export:
`nerfstudio-data` for train / val / test with the initial points of `ply_file_path`, and
`dnerf` (transforms_{train,val,test}.json, with time).

usage: python nerfstudio_check.py EXPORT_DIR
"""

from __future__ import annotations

import importlib.metadata
import json
import sys
from pathlib import Path

from nerfstudio.data.dataparsers.dnerf_dataparser import DNeRFDataParserConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig


def main() -> None:
    export = Path(sys.argv[1])
    meta = json.loads((export / "transforms.json").read_text())
    version = importlib.metadata.version("nerfstudio")
    print(f"  nerfstudio {version}")
    parser = NerfstudioDataParserConfig(
        data=export,
        load_3D_points=True,
        auto_scale_poses=False,
        center_method="none",
        orientation_method="none",
    ).setup()
    for split, key in (("train", "train_filenames"), ("val", "val_filenames"), ("test", "test_filenames")):
        out = parser.get_dataparser_outputs(split=split)
        assert len(out.image_filenames) == len(meta[key]), (split, len(out.image_filenames))
        pts = out.metadata.get("points3D_xyz")
        assert pts is not None, "no points from ply_file_path"
        assert len(pts) > 0, "no points from ply_file_path"
        cx = sorted({round(float(v), 4) for v in out.cameras.cx.ravel()})
        n = len(out.image_filenames)
        print(f"  nerfstudio-data {split}: {n} images, {len(pts)} initial points, cx {cx}")
    dn = DNeRFDataParserConfig(data=export).setup()
    for split in ("train", "val", "test"):
        out = dn.get_dataparser_outputs(split=split)
        times = out.cameras.times
        assert times is not None
        span = f"{float(times.min()):.3f}..{float(times.max()):.3f}"
        print(f"  dnerf {split}: {len(out.image_filenames)} images, time {span}")


if __name__ == "__main__":
    main()
