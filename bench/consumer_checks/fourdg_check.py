"""4DGaussians (at the pinned commit, unmodified) on rigd's 4dgaussians export: its `Scene`
picks the reader by the files of the directory; it must pick PanopticSports and load every view
with its own camera, and the board projected by those cameras must land on the images.

usage: python fourdg_check.py FOURDG_REPO EXPORT_DIR VIEWS_JSON
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from types import SimpleNamespace

import cuda_stubs


def main() -> None:
    repo, export, views = Path(sys.argv[1]), Path(sys.argv[2]).resolve(), Path(sys.argv[3])
    cuda_stubs.install()
    cuda_stubs.torchvision_or_stub()
    sys.path.insert(0, str(repo))
    from scene import Scene  # 4DGaussians' scene/__init__.py

    made = []
    gaussians = SimpleNamespace(  # the model is not under test: Scene only hands it the points
        _deformation=SimpleNamespace(deformation_net=SimpleNamespace(set_aabb=lambda *a: None)),
        create_from_pcd=lambda pcd, extent, maxtime: made.append((len(pcd.points), extent, maxtime)),
    )
    args = SimpleNamespace(
        model_path=str(export / "4dgs-model"),
        source_path=str(export),
        images="images",
        eval=True,
        llffhold=8,
        white_background=False,
        extension=".png",
        add_points=False,
    )
    scene = Scene(args, gaussians, load_iteration=None, shuffle=False)
    print(f"  Scene picked the {scene.dataset_type} reader; maxtime {scene.maxtime}, points {made[0][0]}")
    assert scene.dataset_type == "PanopticSports", scene.dataset_type
    cams = {}
    for split in ("train", "test"):
        md = json.loads((export / f"{split}_meta.json").read_text())
        fns = [fn for row in md["fn"] for fn in row]
        data = (scene.train_camera if split == "train" else scene.test_camera).dataset
        assert len(data) == len(fns), (len(data), len(fns))
        focals = set()
        for fn, item, k in zip(fns, data, (k for row in md["k"] for k in row), strict=True):
            cams[fn] = item["camera"]
            focals.add(round(item["camera"].image_width / (2 * item["camera"].tanfovx), 6))
            assert abs(item["camera"].image_width / (2 * item["camera"].tanfovx) - k[0][0]) < 1e-6
        times = sorted({round(item["time"], 9) for item in data})
        print(f"  {split}: {len(data)} views, own K each (focals {sorted(focals)}), {len(times)} times")
    print("  " + cuda_stubs.check_views(cams, json.loads(views.read_text())))


if __name__ == "__main__":
    main()
