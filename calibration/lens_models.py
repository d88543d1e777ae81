# ruff: noqa: N803, N806  (K follows the notation of the calibration literature)
"""Lens models and their selection: one OpenCV fit per model, k-fold cross-validation over views,
and the walk from simple to rich that keeps a richer model only when it predicts held-out views
better by a margin ("a complex camera model may not be always better": in-sample RMS always drops).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel

from calibration.boards import Detection
from calibration.errors import CalibrationError

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class LensModel:
    """A distortion model as a set of cv2.calibrateCamera flags; `params` are its free terms."""

    name: str
    flags: int
    params: tuple[str, ...]
    n_coeffs: int  # length of the OpenCV distortion vector it produces

    @property
    def n_params(self) -> int:
        return 4 + len(self.params)


_RAT = cv2.CALIB_RATIONAL_MODEL


#: From simplest to richest; selection walks this list.
LENS_MODELS: tuple[LensModel, ...] = (
    LensModel("k1k2", cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST, ("k1", "k2"), 5),
    LensModel("k1k2k3", cv2.CALIB_ZERO_TANGENT_DIST, ("k1", "k2", "k3"), 5),
    LensModel("k1k2+tangential", cv2.CALIB_FIX_K3, ("k1", "k2", "p1", "p2"), 5),
    LensModel("k1k2k3+tangential", 0, ("k1", "k2", "p1", "p2", "k3"), 5),
    LensModel("rational", _RAT, ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"), 8),
    LensModel(
        "rational+thin_prism",
        _RAT | cv2.CALIB_THIN_PRISM_MODEL,
        ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4"),
        12,
    ),
)


MODELS_BY_NAME = {m.name: m for m in LENS_MODELS}


#: Order of cv2.calibrateCameraExtended's stdDeviationsIntrinsics.
STD_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4")


#: OpenCV's order of the distortion coefficients.
DIST_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4")


#: A richer model must lower the cross-validated RMS by this fraction to be kept.
CV_MARGIN = 0.02


_TERM = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)


class ModelScore(BaseModel):
    """Cross-validation result of one lens model."""

    model: str
    n_params: int
    train_rms_px: float | None
    cv_rms_px: float | None
    note: str = ""


@dataclass
class ModelFit:
    """One OpenCV calibration of a set of views under one lens model."""

    rms: float
    K: F64
    dist: F64
    rvecs: list[F64]
    tvecs: list[F64]
    std: F64
    per_view: F64


def _obj(d: Detection) -> NDArray[np.float32]:
    return d.object_points.astype(np.float32).reshape(-1, 1, 3)


def _img(d: Detection) -> NDArray[np.float32]:
    return d.image_points.astype(np.float32).reshape(-1, 1, 2)


def fit_model(dets: Sequence[Detection], size: tuple[int, int], model: LensModel) -> ModelFit:
    """cv2.calibrateCameraExtended with the model's flags; CalibrationError if OpenCV refuses."""
    try:
        rms, K, dist, rvecs, tvecs, std, _, per_view = cv2.calibrateCameraExtended(  # type: ignore[call-overload]
            [_obj(d) for d in dets],
            [_img(d) for d in dets],
            size,
            None,  # OpenCV allocates K and dist itself
            None,
            flags=model.flags,
            criteria=_TERM,
        )
    except cv2.error as exc:
        names = ", ".join(d.name for d in dets[:5])
        raise CalibrationError(
            f"OpenCV could not calibrate model {model.name} from {len(dets)} views ({names}...): {exc.err}"
        ) from exc
    dist = np.asarray(dist, np.float64).ravel()
    dist = np.concatenate([dist, np.zeros(max(0, model.n_coeffs - dist.size))])[: model.n_coeffs]
    return ModelFit(
        float(rms),
        np.asarray(K, np.float64),
        dist,
        [np.asarray(r, np.float64).ravel() for r in rvecs],
        [np.asarray(t, np.float64).ravel() for t in tvecs],
        np.asarray(std, np.float64).ravel(),
        np.asarray(per_view, np.float64).ravel(),
    )


def reprojection_residuals(d: Detection, K: F64, dist: F64, rvec: F64, tvec: F64) -> F64:
    proj, _ = cv2.projectPoints(d.object_points.reshape(-1, 1, 3), rvec, tvec, K, dist)
    return np.asarray(proj.reshape(-1, 2) - d.image_points, np.float64)


def _heldout_sq_errors(d: Detection, K: F64, dist: F64) -> F64:
    """Squared residuals of a view not used for fitting: its pose comes from PnP with the fitted
    intrinsics, so only the lens model is being judged."""
    ok, rvec, tvec = cv2.solvePnP(d.object_points, d.image_points, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibrationError(f"view {d.name}: PnP failed on a held-out view")
    rvec, tvec = cv2.solvePnPRefineLM(d.object_points, d.image_points, K, dist, rvec, tvec)
    res = reprojection_residuals(
        d, K, dist, np.asarray(rvec, np.float64).ravel(), np.asarray(tvec, np.float64).ravel()
    )
    return np.asarray((res**2).sum(axis=1), np.float64)


def cross_validate(
    dets: Sequence[Detection], size: tuple[int, int], model: LensModel, folds: int = 5
) -> float:
    """RMS reprojection error (px) of held-out views, k-fold over views (view i in fold i % k)."""
    k = min(folds, len(dets))
    sq: list[F64] = []
    for f in range(k):
        train = [d for i, d in enumerate(dets) if i % k != f]
        test = [d for i, d in enumerate(dets) if i % k == f]
        fit = fit_model(train, size, model)
        sq.extend(_heldout_sq_errors(d, fit.K, fit.dist) for d in test)
    return float(math.sqrt(np.concatenate(sq).mean()))


def select_model(
    dets: Sequence[Detection], size: tuple[int, int], candidates: Sequence[LensModel] = LENS_MODELS
) -> tuple[LensModel, list[ModelScore]]:
    """Walk the candidates from simple to rich; keep a richer model only when its cross-validated
    RMS beats the kept one's by CV_MARGIN. Models OpenCV cannot fit are scored None with the reason."""
    scores: list[ModelScore] = []
    best: LensModel | None = None
    best_cv = math.inf
    for model in sorted(candidates, key=lambda m: m.n_params):
        n_obs = 2 * sum(d.n for d in dets)
        if n_obs < 3 * (model.n_params + 6 * len(dets)):
            scores.append(_unscored(model, "too few corners for this many parameters"))
            continue
        try:
            train = fit_model(dets, size, model).rms
            cv_rms = cross_validate(dets, size, model)
        except CalibrationError as exc:
            log.warning("model %s not scored: %s", model.name, exc)
            scores.append(_unscored(model, str(exc)))
            continue
        kept = best is None or cv_rms < best_cv * (1.0 - CV_MARGIN)
        scores.append(
            ModelScore(
                model=model.name,
                n_params=model.n_params,
                train_rms_px=train,
                cv_rms_px=cv_rms,
                note="kept" if kept or best is None else _not_kept(model, cv_rms, best, best_cv),
            )
        )
        log.info(
            "model %s: train RMS %.4f px, held-out RMS %.4f px%s",
            model.name,
            train,
            cv_rms,
            " (kept)" if kept else "",
        )
        if kept:
            best, best_cv = model, cv_rms
    if best is None:
        raise CalibrationError(f"no lens model could be fitted to {len(dets)} views")
    for s in scores:
        if s.note == "kept" and s.model != best.name:
            s.note = "beaten by a richer model by more than the margin"
    for s in scores:
        if s.model == best.name:
            s.note = "chosen"
    return best, scores


def _not_kept(model: LensModel, cv_rms: float, kept: LensModel, kept_cv: float) -> str:
    """Why a richer model lost: its held-out RMS did not beat the kept one's by CV_MARGIN, so its
    extra parameters would fit noise rather than the lens."""
    gain = 1.0 - cv_rms / kept_cv
    n = model.n_params - kept.n_params
    extra = f"{n} more parameter{'s' if n != 1 else ''}"
    if gain <= 0:
        return f"held-out RMS no lower than {kept.name}'s: {extra} for nothing"
    return (
        f"held-out RMS {gain * 100:.1f} % lower than {kept.name}'s, less than the {CV_MARGIN * 100:g} % "
        f"asked of {extra}"
    )


def _unscored(model: LensModel, why: str) -> ModelScore:
    return ModelScore(model=model.name, n_params=model.n_params, train_rms_px=None, cv_rms_px=None, note=why)


def max_distortion_px(K: F64, dist: F64, size: tuple[int, int]) -> float:
    """Largest shift (px) the lens model applies along the image border: undistort border points
    and compare (a quick measure of how strong the distortion is)."""
    w, h = size
    xs = np.linspace(0, w - 1, 33)
    ys = np.linspace(0, h - 1, 33)
    border = np.concatenate(
        [
            np.stack([xs, np.zeros_like(xs)], 1),
            np.stack([xs, np.full_like(xs, h - 1)], 1),
            np.stack([np.zeros_like(ys), ys], 1),
            np.stack([np.full_like(ys, w - 1), ys], 1),
        ]
    )
    und = cv2.undistortPoints(border.reshape(-1, 1, 2), K, dist, P=K).reshape(-1, 2)
    return float(np.linalg.norm(und - border, axis=1).max())
