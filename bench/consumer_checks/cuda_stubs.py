"""ONLY for the scratch venvs of `python -m bench.consumers`: the CUDA-only pieces that
Dynamic3DGaussians and 4DGaussians import, so their (unmodified) loaders run on a CPU.

- `diff_gaussian_rasterization`: GaussianRasterizationSettings keeps its keyword arguments (the
  loaders build one per camera with `setup_camera`); GaussianRasterizer is never called.
- `simple_knn._C.distCUDA2`: raises if called (the loaders do not call it).
- `Tensor.cuda()` returns the tensor, `torch.tensor(..., device="cuda")` makes a CPU tensor.

`project` is the rasterizer's projection of a point (cuda_rasterizer/auxiliary.h):
p_hom = [X, 1] @ projmatrix, ndc = p_hom[:3] / p_hom[3], pixel = ((ndc + 1) * S - 1) / 2, which
puts pixel (0, 0)'s centre at 0: the image the rasterizer draws has pixel centres at integers.
"""

from __future__ import annotations

import sys
import types

import numpy as np
import torch


class GaussianRasterizationSettings:
    def __init__(self, **kwargs: object) -> None:
        self.__dict__.update(kwargs)


def install() -> None:
    rast = types.ModuleType("diff_gaussian_rasterization")
    rast.GaussianRasterizationSettings = GaussianRasterizationSettings  # type: ignore[attr-defined]
    rast.GaussianRasterizer = object  # type: ignore[attr-defined]
    sys.modules["diff_gaussian_rasterization"] = rast
    knn = types.ModuleType("simple_knn")
    knn_c = types.ModuleType("simple_knn._C")

    def dist_cuda2(*_: object) -> None:
        raise RuntimeError("simple_knn is a CUDA extension, stubbed in this check")

    knn_c.distCUDA2 = dist_cuda2  # type: ignore[attr-defined]
    knn._C = knn_c  # type: ignore[attr-defined]
    sys.modules["simple_knn"], sys.modules["simple_knn._C"] = knn, knn_c
    torch.Tensor.cuda = lambda self, *a, **k: self  # type: ignore[method-assign]
    tensor = torch.tensor

    def cpu_tensor(*args: object, device: object = None, **kwargs: object) -> torch.Tensor:
        return tensor(*args, **kwargs)  # type: ignore[arg-type]

    torch.tensor = cpu_tensor  # type: ignore[assignment]
    print("  (stubbed here only: diff_gaussian_rasterization, simple_knn, Tensor.cuda -> CPU)")


def torchvision_or_stub() -> None:
    """Import torchvision; where only its CUDA build can be installed (its C ops fail to register
    on a CPU torch) put a stub in its place whose transforms raise when used: 4DGaussians'
    dataset_readers imports it at module level and its PanopticSports reader never calls it."""
    try:
        import torchvision  # noqa: F401
    except RuntimeError as exc:
        why = str(exc)
        tv = types.ModuleType("torchvision")
        tf = types.ModuleType("torchvision.transforms")

        def unavailable(*_: object, **__: object) -> None:
            raise RuntimeError(f"torchvision is stubbed in this check ({why})")

        tf.ToTensor = unavailable  # type: ignore[attr-defined]
        tv.transforms = tf  # type: ignore[attr-defined]
        sys.modules["torchvision"], sys.modules["torchvision.transforms"] = tv, tf
        print(f"  (stubbed here only: torchvision, whose CUDA build fails on this CPU torch: {why})")


def project(cam: GaussianRasterizationSettings, X: np.ndarray) -> np.ndarray:  # noqa: N803
    full = np.asarray(cam.projmatrix, np.float64).reshape(4, 4)  # type: ignore[attr-defined]
    p = np.c_[X, np.ones(len(X))] @ full
    ndc = p[:, :3] / p[:, 3:4]
    size = np.array([cam.image_width, cam.image_height], np.float64)  # type: ignore[attr-defined]
    return ((ndc[:, :2] + 1.0) * size - 1.0) * 0.5


def check_views(cams: dict[str, GaussianRasterizationSettings], views: list[dict[str, object]]) -> str:
    """Ground-truth corners projected as the rasterizer does against the corners found in the
    exported images: mean and worst view error, and the mean residual (half a pixel off in the
    principal point shows as a bias of 0.5)."""
    errs, res = [], []
    for v in views:
        cam = cams.get(str(v["fn"]))
        if cam is None:
            continue
        uv = project(cam, np.asarray(v["X"], np.float64))
        found = np.asarray(v["uv"], np.float64)
        errs.append(float(np.linalg.norm(uv - found, axis=1).mean()))
        res.append(uv - found)
    assert errs, "no view with the board"
    bias = np.concatenate(res).mean(axis=0)
    line = (
        f"{len(errs)} views: board corners projected by its camera within mean {np.mean(errs):.3f} px, "
        f"worst view {max(errs):.3f} px, bias ({bias[0]:+.3f}, {bias[1]:+.3f}) px"
    )
    assert max(errs) < 0.5, line
    assert np.all(np.abs(bias) < 0.15), line
    return line
