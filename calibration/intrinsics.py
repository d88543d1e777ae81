# ruff: noqa: N806  (K, R, T, J follow the notation of the calibration literature)
"""Intrinsic calibration with lens-model selection, outlier-view rejection and uncertainty.

Procedure (course notes: Zhang's closed form, then Levenberg-Marquardt, both inside
cv2.calibrateCamera): detect the board in every image, drop blurred views, pick the lens model by
k-fold cross-validation over views, calibrate, reject views whose error is far above the others
(one at a time, re-calibrating in between), and report parameter standard deviations plus
warnings about degenerate view sets. "A complex camera model may not be always better": a richer
model is kept only when it predicts *held-out* views better than the simpler one by a margin, since
its in-sample RMS always goes down.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, Field

from calibration.boards import (
    DEFAULT_MAX_EDGE_WIDTH_PX,
    BoardSpec,
    Detection,
    detect,
    load_image,
    nearby_boards,
)
from calibration.errors import CalibrationError, NoBoardFoundError
from calibration.lens_models import (
    F64,
    LENS_MODELS,
    MODELS_BY_NAME,
    STD_NAMES,
    LensModel,
    ModelFit,
    ModelScore,
    fit_model,
    max_distortion_px,
    reprojection_residuals,
    select_model,
)

log = logging.getLogger(__name__)


#: Fewest usable views for cross-validation (each training set needs 3+ views).
MIN_VIEWS_FOR_CV = 5
RECOMMENDED_VIEWS = 10
#: Outlier views: RMS above max(OUTLIER_MEDIAN_FACTOR * median, median + OUTLIER_MAD_SIGMAS * sigma_MAD).
OUTLIER_MEDIAN_FACTOR = 2.5
OUTLIER_MAD_SIGMAS = 5.0
#: Median board area (fraction of the image) below which the board is called small.
SMALL_BOARD_FRAC = 0.04


class ViewResult(BaseModel):
    """One view kept in the calibration: its error, pose and per-corner residuals (pixels)."""

    name: str
    rms_px: float
    n_points: int
    rvec: list[float]
    tvec: list[float]
    tilt_deg: float = Field(description="angle between the board normal and the optical axis")
    board_area_frac: float = Field(description="convex hull of the corners / image area")
    edge_width_px: float | None = None
    ids: list[int]
    image_points: list[list[float]]
    residuals: list[list[float]] = Field(description="projected minus detected, per corner")


class RejectedView(BaseModel):
    name: str
    reason: str


class IntrinsicsResult(BaseModel):
    """Intrinsic calibration of one camera. `dist` is in OpenCV order (k1 k2 p1 p2 k3 [k4 k5 k6
    [s1 s2 s3 s4]]); `std_devs` holds one standard deviation of every free parameter."""

    camera: str
    board: str
    image_size: tuple[int, int]
    model: str
    K: list[list[float]]
    dist: list[float]
    rms_px: float
    std_devs: dict[str, float]
    views: list[ViewResult]
    rejected: list[RejectedView] = []
    warnings: list[str] = []
    model_scores: list[ModelScore] = []

    def camera_matrix(self) -> F64:
        return np.asarray(self.K, np.float64)

    def dist_coeffs(self) -> F64:
        return np.asarray(self.dist, np.float64)

    def summary(self) -> dict[str, object]:
        """The result without per-corner data: what `--json` prints."""
        d = self.model_dump(exclude={"views"})
        d["per_view_rms_px"] = {v.name: v.rms_px for v in self.views}
        return d


def _tilt_deg(rvec: F64) -> float:
    R, _ = cv2.Rodrigues(rvec)
    return float(math.degrees(math.acos(min(1.0, abs(float(R[2, 2]))))))


def _hull_frac(d: Detection) -> float:
    hull = cv2.convexHull(d.image_points.astype(np.float32))
    return float(cv2.contourArea(hull)) / float(d.image_size[0] * d.image_size[1])


def _coverage_frac(dets: Sequence[Detection], size: tuple[int, int], cells: int = 8) -> float:
    """Fraction of an 8x8 grid of image cells that hold at least one detected corner."""
    w, h = size
    hit = np.zeros((cells, cells), bool)
    for d in dets:
        cx = np.clip((d.image_points[:, 0] / w * cells).astype(int), 0, cells - 1)
        cy = np.clip((d.image_points[:, 1] / h * cells).astype(int), 0, cells - 1)
        hit[cy, cx] = True
    return float(hit.mean())


def _degeneracy_warnings(
    dets: Sequence[Detection], fit: ModelFit, size: tuple[int, int], model: LensModel
) -> list[str]:
    warnings: list[str] = []
    n = len(dets)
    if n < RECOMMENDED_VIEWS:
        warnings.append(
            f"only {n} usable views; {RECOMMENDED_VIEWS}-20 are recommended, so parameters are poorly "
            "constrained (model selection and outlier rejection are limited too)"
        )
    tilts = [_tilt_deg(r) for r in fit.rvecs]
    if max(tilts) < 15.0:
        warnings.append(
            f"all views are nearly fronto-parallel (largest board tilt {max(tilts):.1f} deg): focal length "
            "and distance cannot be told apart; tilt the board 20-45 deg in several directions"
        )
    areas = [_hull_frac(d) for d in dets]
    if float(np.median(areas)) < SMALL_BOARD_FRAC:
        warnings.append(
            f"the board is small in the image (median {100 * float(np.median(areas)):.1f} % of the image "
            "area): move it closer so that corners constrain the distortion"
        )
    cov = _coverage_frac(dets, size)
    if cov < 0.5:
        warnings.append(
            f"corners cover only {100 * cov:.0f} % of the image (8x8 cells): the image edges, where "
            "distortion is largest, are extrapolated; show the board near the borders and corners"
        )
    shift = max_distortion_px(fit.K, fit.dist, size)
    if shift > 0.05 * math.hypot(*size):
        warnings.append(
            f"strong distortion: the model moves the image border by up to {shift:.0f} px; check the "
            "undistorted image (a fisheye model may fit this lens better)"
        )
    fx_std = _std_map(fit, model).get("fx", 0.0)
    if fx_std > 0.01 * fit.K[0, 0]:
        warnings.append(f"focal length uncertain: fx std {fx_std:.2f} px > 1 % of fx; add tilted views")
    return warnings


def _std_map(fit: ModelFit, model: LensModel) -> dict[str, float]:
    free = {"fx", "fy", "cx", "cy", *model.params}
    return {n: float(fit.std[i]) for i, n in enumerate(STD_NAMES) if n in free and i < fit.std.size}


def _outlier_limit(rms: F64) -> float:
    med = float(np.median(rms))
    mad = float(np.median(np.abs(rms - med))) * 1.4826
    return max(OUTLIER_MEDIAN_FACTOR * med, med + OUTLIER_MAD_SIGMAS * mad)


def calibrate_intrinsics(
    detections: Sequence[Detection],
    board: BoardSpec,
    camera: str = "cam0",
    model: str = "auto",
    max_edge_width_px: float = DEFAULT_MAX_EDGE_WIDTH_PX,
    reject_outliers: bool = True,
    rejected: Sequence[RejectedView] = (),
    warnings: Sequence[str] = (),
) -> IntrinsicsResult:
    """Calibrate one camera from board detections (see the module docstring for the steps).

    `model` is "auto" (cross-validated selection) or a name from LENS_MODELS. `rejected` and
    `warnings` from the detection stage are carried into the result.
    """
    rej = list(rejected)
    warn = list(warnings)
    size = _image_size(detections, board, camera, rej)
    usable = _usable_views(detections, max_edge_width_px, rej)
    if len(usable) < 2:
        raise CalibrationError(
            f"camera {camera}: {len(usable)} usable view(s) of {board}; need at least 2 "
            f"(rejected: {'; '.join(f'{r.name}: {r.reason}' for r in rej) or 'none'})"
        )
    lens, scores = _choose_lens(model, usable, size, warn)
    fit = fit_model(usable, size, lens)
    if reject_outliers:
        fit = _reject_outlier_views(usable, size, lens, fit, camera, rej)
    warn.extend(_degeneracy_warnings(usable, fit, size, lens))
    for w in warn:  # returned in .warnings: the caller reports them, once
        log.info("camera %s: %s", camera, w)
    return IntrinsicsResult(
        camera=camera,
        board=str(board),
        image_size=size,
        model=lens.name,
        K=fit.K.tolist(),
        dist=fit.dist.tolist(),
        rms_px=fit.rms,
        std_devs=_std_map(fit, lens),
        views=_view_results(usable, fit),
        rejected=rej,
        warnings=warn,
        model_scores=scores,
    )


def _image_size(
    detections: Sequence[Detection], board: BoardSpec, camera: str, rejected: Sequence[RejectedView]
) -> tuple[int, int]:
    """The one image size of all detections; NoBoardFoundError when there are none."""
    if not detections:
        raise NoBoardFoundError(
            f"camera {camera}: board {board} was not found in any image"
            + (f" ({len(rejected)} images tried)" if rejected else "")
        )
    sizes = {d.image_size for d in detections}
    if len(sizes) != 1:
        raise CalibrationError(f"camera {camera}: images have different sizes {sorted(sizes)}")
    return next(iter(sizes))


def _usable_views(
    detections: Sequence[Detection], max_edge_width_px: float, rejected: list[RejectedView]
) -> list[Detection]:
    """Views with enough corners and sharp enough edges; the others go to `rejected` with why."""
    usable: list[Detection] = []
    for d in detections:
        if d.n < 6:
            rejected.append(RejectedView(name=d.name, reason=f"only {d.n} corners detected (need 6)"))
        elif math.isfinite(d.edge_width_px) and d.edge_width_px > max_edge_width_px:
            rejected.append(
                RejectedView(
                    name=d.name,
                    reason=f"blurred: edge width {d.edge_width_px:.1f} px > {max_edge_width_px:.1f} px "
                    "(motion blur or focus)",
                )
            )
        else:
            usable.append(d)
    return usable


def _choose_lens(
    model: str, usable: Sequence[Detection], size: tuple[int, int], warnings: list[str]
) -> tuple[LensModel, list[ModelScore]]:
    """The named model, or ("auto") the cross-validated choice; the simplest when too few views."""
    if model != "auto":
        if model not in MODELS_BY_NAME:
            raise CalibrationError(f"unknown lens model {model!r}; choose from {', '.join(MODELS_BY_NAME)}")
        return MODELS_BY_NAME[model], []
    if len(usable) < MIN_VIEWS_FOR_CV:
        lens = LENS_MODELS[0]
        warnings.append(
            f"{len(usable)} views are too few for cross-validated model selection "
            f"(need {MIN_VIEWS_FOR_CV}); using the simplest model {lens.name}"
        )
        return lens, []
    return select_model(usable, size)


def _reject_outlier_views(
    usable: list[Detection],
    size: tuple[int, int],
    lens: LensModel,
    fit: ModelFit,
    camera: str,
    rejected: list[RejectedView],
) -> ModelFit:
    """Drop the worst view while its error is far above the others, refitting in between; `usable`
    loses the dropped views. One at a time, since one bad view inflates every other's error."""
    while len(usable) > max(MIN_VIEWS_FOR_CV, 3):
        limit = _outlier_limit(fit.per_view)
        worst = int(np.argmax(fit.per_view))
        if fit.per_view[worst] <= limit:
            break
        bad = usable.pop(worst)
        reason = (
            f"reprojection RMS {fit.per_view[worst]:.3f} px > limit {limit:.3f} px "
            f"(median {float(np.median(fit.per_view)):.3f} px): wrong corners, blur or a moved board"
        )
        log.info("camera %s: rejecting view %s: %s", camera, bad.name, reason)
        rejected.append(RejectedView(name=bad.name, reason=reason))
        fit = fit_model(usable, size, lens)
    return fit


def _view_results(usable: Sequence[Detection], fit: ModelFit) -> list[ViewResult]:
    return [
        ViewResult(
            name=d.name,
            rms_px=float(e),
            n_points=d.n,
            rvec=rv.tolist(),
            tvec=tv.tolist(),
            tilt_deg=_tilt_deg(rv),
            board_area_frac=_hull_frac(d),
            edge_width_px=d.edge_width_px if math.isfinite(d.edge_width_px) else None,
            ids=d.ids.tolist(),
            image_points=d.image_points.tolist(),
            residuals=reprojection_residuals(d, fit.K, fit.dist, rv, tv).tolist(),
        )
        for d, rv, tv, e in zip(usable, fit.rvecs, fit.tvecs, fit.per_view, strict=True)
    ]


def detect_images(
    paths: Sequence[str | Path], board: BoardSpec, on_image: Callable[[int, int], None] | None = None
) -> tuple[list[Detection], list[RejectedView], list[str]]:
    """Detect the board in image files: detections, rejected files (board not found) and warnings
    (board partly outside). A file that cannot be read or has another size raises, naming it.
    `on_image(done, total)` is told before each file and once all are done (a progress display)."""
    dets: list[Detection] = []
    rej: list[RejectedView] = []
    warn: list[str] = []
    size: tuple[int, int] | None = None
    for i, p in enumerate(paths):
        if on_image is not None:
            on_image(i, len(paths))
        img = load_image(p)
        this = (int(img.shape[1]), int(img.shape[0]))
        if size is not None and this != size:
            raise CalibrationError(f"{p}: image size {this} differs from the first image's {size}")
        size = this
        d = detect(img, board, name=Path(p).name)
        if d is None:
            rej.append(
                RejectedView(
                    name=Path(p).name,
                    reason=f"board {board} not found (not in view, partly outside the image, or too blurred)",
                )
            )
            continue
        near = (d.image_points < 3).any(axis=1) | (d.image_points > np.array(this) - 4).any(axis=1)
        if not d.is_complete(board) or near.any():
            warn.append(
                f"{Path(p).name}: board partly outside the image ({d.n} of {board.n_corners} corners seen"
                f"{', some at the border' if near.any() else ''})"
            )
        dets.append(d)
    if rej and len(rej) > len(dets):
        warn.append(f"board not found in {len(rej)} of {len(rej) + len(dets)} images; check the board spec")
    if on_image is not None:
        on_image(len(paths), len(paths))
    return dets, rej, warn


#: Images that failed detection on which the nearby board sizes are tried.
_PROBE_IMAGES = 3


def _size(board: BoardSpec) -> str:
    return f"{board.cols}x{board.rows}"


def suggest_board(paths: Sequence[str | Path], board: BoardSpec, failed: Sequence[str | Path]) -> str | None:
    """'N of M show CxR: use --board SPEC' for the nearby size found most, or None.

    The nearby sizes are tried on a few `failed` images spread over the list; the best one is then
    counted over all `paths`.
    """
    if not failed:
        return None
    step = max(1, len(failed) // _PROBE_IMAGES)
    probes = [load_image(p) for p in list(failed)[::step][:_PROBE_IMAGES]]
    best: BoardSpec | None = None
    best_hits = 0
    for alt in nearby_boards(board):
        hits = sum(detect(img, alt) is not None for img in probes)
        if hits > best_hits:
            best, best_hits = alt, hits
    if best is None:
        return None
    count = sum(detect(load_image(p), best) is not None for p in paths)
    return f"{count} of {len(paths)} show {_size(best)}: use --board {best}"


def calibrate_images(
    paths: Sequence[str | Path],
    board: BoardSpec,
    camera: str = "cam0",
    model: str = "auto",
    max_edge_width_px: float = DEFAULT_MAX_EDGE_WIDTH_PX,
    allow_few_views: bool = False,
    on_image: Callable[[int, int], None] | None = None,
) -> IntrinsicsResult:
    """Detect and calibrate from image files; NoBoardFoundError names the files when none shows it.

    When the board is not found in most images (and not `allow_few_views`), NoBoardFoundError
    names a nearby board size that is found, or says how to go on with the few views.
    """
    if not paths:
        raise CalibrationError(f"camera {camera}: no images given")
    dets, rej, warn = detect_images(paths, board, on_image)
    if 2 * len(rej) > len(paths) and not allow_few_views:
        names = {r.name for r in rej}
        hint = suggest_board(paths, board, [p for p in paths if Path(p).name in names])
        shown = f"camera {camera}: {len(dets)} of {len(paths)} images show a {_size(board)} board"
        if hint is not None:
            raise NoBoardFoundError(f"{shown}; {hint}")
        if dets:
            raise NoBoardFoundError(
                f"{shown}, and no nearby board size is found more often; check the images, "
                "or pass --allow-few-views to calibrate from these views"
            )
    if not dets:
        shown = ", ".join(str(Path(p).name) for p in list(paths)[:5])
        raise NoBoardFoundError(
            f"camera {camera}: board {board} not found in any of {len(paths)} images ({shown}"
            f"{'...' if len(paths) > 5 else ''}); check the inner-corner count of the spec"
        )
    return calibrate_intrinsics(
        dets,
        board,
        camera=camera,
        model=model,
        max_edge_width_px=max_edge_width_px,
        rejected=rej,
        warnings=warn,
    )


def undistort(
    image: NDArray[np.generic], result: IntrinsicsResult, alpha: float = 0.0
) -> NDArray[np.generic]:
    """The image undistorted with the calibration (alpha 0: only valid pixels, 1: all pixels)."""
    K, dist = result.camera_matrix(), result.dist_coeffs()
    newK, _ = cv2.getOptimalNewCameraMatrix(K, dist, result.image_size, alpha)
    return np.asarray(cv2.undistort(np.asarray(image, np.uint8), K, dist, None, newK))
