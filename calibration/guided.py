"""Guided calibration session: live frames in, capture decisions and "show me this next" out.

Why: a technician waving a board in front of a camera cannot judge which views are still missing.
The session watches every frame, keeps a view only when it is worth keeping, and tells the
technician where to put the board next and when to stop.

Per frame (`GuidedSession.offer`):

1. Detect the board (`calibration.boards.detect`). With `fast_detect` (default) a chessboard is
   first looked for with the classic detector alone (~10 ms when absent): detect()'s fallback to
   the SB detector costs ~100 ms on a frame without the board and would stall a live feed. (The
   cheaper cv2.checkChessboard misses boards with squares under ~10 px, so it is not used.) Set
   `fast_detect=False` for lenses whose views only the SB detector finds (strong distortion).
2. *Still*: the board smears by less than `still_px` during one exposure. With `exposure_us`
   known, the smear is the largest corner speed (corner motion since the previous offered frame
   over the time between the two) times the exposure; without it, the corner motion itself.
   Why not the raw motion between offered frames: a live feed skips frames while the session
   works, so that motion grows with the host's load, not with the blur; on the sim rig (board
   moving ~1 px per 33 ms frame, 8 ms exposure) it measured 1.5-6 px between offered frames
   although the smear is ~0.2 px, and a 1 px limit kept 2 views in 120 s.
   *Sharp*: the board's edge width is below `max_edge_width_px` (the sharpness measure of boards.py).
3. *Novel*: the view is not a near-duplicate of a kept one (mean corner distance < `dup_px` and
   tilt within `dup_deg` of it), and its coverage bin holds fewer than `max_per_bin` views.
   Coverage is counted in bins (`calibration.view_planning`).
4. A still, sharp, novel view is captured. Once `min_views` are kept, every capture re-runs the
   calibration (fast model, k1k2 by default, `cv2.calibrateCameraExtended`) for the poses the hint
   needs. Once `done_views` are kept, every capture also runs the calibration that `result()`
   returns and a caller writes (`calibrate_intrinsics`: outlier views rejected); the session is
   done when that fit uses at least `done_views` views (the report's recommendation,
   intrinsics.RECOMMENDED_VIEWS, so a finished session never gets the report's "too few views"
   warning) and its std devs of fx, fy, cx, cy are all <= `target_sigma_px`. Why that fit and
   not the fast one: the two differ by the rejected views, and a stop rule on the fast fit kept a
   session running until time ran out while the file it wrote had met the target long before.
   The sigmas shown are those of the written fit once there is one.

Next hint (what to show next): `calibration.view_planning` (the information-matrix method).
A pose hinted for `hint_patience_s` in all (frame time with the board in view, summed over every
time it was the hint) without a capture there is a pose this board
does not reach (a mount, a robot arm, the sim's scripted motion): its bin is no longer hinted and
the next best one is, so the technician is never told the same unreachable pose for ever.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Literal, NamedTuple

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, Field

from calibration.boards import DEFAULT_MAX_EDGE_WIDTH_PX, BoardSpec, Detection, detect
from calibration.errors import CalibrationError
from calibration.intrinsics import RECOMMENDED_VIEWS, IntrinsicsResult, calibrate_intrinsics
from calibration.lens_models import MODELS_BY_NAME, fit_model
from calibration.view_planning import (
    FLAT_DEG,
    TILT_BINS,
    TILT_DEG,
    Candidate,
    ViewPlanner,
    tilt_angles,
    tilt_bin,
)

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

_TILT_TEXT = {
    "facing": "hold it facing the camera (tilt under {flat:.0f} deg)",
    "right-away": "turn it ~{deg:.0f} deg about the vertical axis, right edge away from the camera",
    "left-away": "turn it ~{deg:.0f} deg about the vertical axis, left edge away from the camera",
    "bottom-away": "tilt it ~{deg:.0f} deg about the horizontal axis, bottom edge away from the camera",
    "top-away": "tilt it ~{deg:.0f} deg about the horizontal axis, top edge away from the camera",
}
#: The intrinsics whose uncertainty the session drives down (and reports).
SIGMA_NAMES: tuple[str, ...] = ("fx", "fy", "cx", "cy")


class Feedback(BaseModel):
    """What the session says about one offered frame (and the session as a whole)."""

    t_us: int
    detected: bool
    n_corners: int = 0
    motion_px: float | None = Field(None, description="largest corner motion since the previous frame")
    blur_px: float | None = Field(None, description="largest corner smear during one exposure (px)")
    still: bool = False
    edge_width_px: float | None = None
    sharp: bool = False
    captured: bool = False
    reason: str = Field(description="why the frame was or was not captured")
    n_views: int
    coverage: list[list[int]] = Field(
        description="views per bin: rows = grid cells (row-major), cols = TILT_BINS"
    )
    cells_covered: float = Field(description="fraction of grid cells holding a view")
    tilts_covered: float = Field(description="fraction of tilt bins holding a view")
    n_used: int | None = Field(
        None, description="views the written fit uses (n_views less the outliers it rejected); None before it"
    )
    next_hint: str
    hint_cell: str = ""
    hint_tilt: str = ""
    sigmas: dict[str, float] = Field(
        default_factory=dict,
        description="std devs (px) of fx fy cx cy: of the written fit once there is one, else of the "
        "running fit",
    )
    rms_px: float | None = None
    done: bool = False


@dataclass
class _View:
    det: Detection
    t_us: int
    rvec: F64
    tvec: F64
    cell: int
    tilt: int
    angles: tuple[float, float]  # (about vertical, about horizontal), degrees


class _FrameState(NamedTuple):
    motion: float | None
    still: bool
    sharp: bool
    blur: float | None = None


@dataclass
class GuidedSession:
    """Live guided calibration of one camera (see the module docstring for the method).

    `offer(image, t_us)` per frame; `result()` for the final calibration.
    """

    board: BoardSpec
    image_size: tuple[int, int]
    target_sigma_px: float = 0.5
    still_px: float = 1.0
    min_views: int = 6
    grid: tuple[int, int] = (3, 3)  # (cols, rows) of coverage cells
    max_edge_width_px: float = DEFAULT_MAX_EDGE_WIDTH_PX
    dup_px: float | None = None  # default: 5 % of the image diagonal
    dup_deg: float = 10.0
    max_per_bin: int = 3
    model: str = "k1k2"
    done_views: int = RECOMMENDED_VIEWS  # fewest views the written fit uses before the session is done
    hint_patience_s: float = 10.0  # a hint no capture answered for this long is not hinted again
    hint_method: Literal["information", "emptiest"] = "information"
    fast_detect: bool = True
    exposure_us: float | None = None  # with it, `still_px` bounds the smear in one exposure
    views: list[_View] = field(default_factory=list, init=False)
    view_errors: list[float] = field(default_factory=list, init=False)
    _prev: Detection | None = field(default=None, init=False, repr=False)
    _prev_t: int | None = field(default=None, init=False, repr=False)
    _K: F64 = field(init=False, repr=False)
    _dist: F64 = field(init=False, repr=False)
    _sigmas: dict[str, float] = field(default_factory=dict, init=False)
    _rms: float | None = field(default=None, init=False)
    _hint: Candidate | None = field(default=None, init=False, repr=False)
    _planner: ViewPlanner = field(init=False, repr=False)
    _waited_us: dict[tuple[int, int], int] = field(default_factory=dict, init=False, repr=False)
    _unreachable: set[tuple[int, int]] = field(default_factory=set, init=False, repr=False)
    _final: IntrinsicsResult | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.model not in MODELS_BY_NAME:
            raise CalibrationError(
                f"unknown lens model {self.model!r}; choose from {', '.join(MODELS_BY_NAME)}"
            )
        if self.min_views < 3:
            raise CalibrationError(
                f"min_views must be >= 3 (OpenCV needs 3 views for a model), got {self.min_views}"
            )
        w, h = self.image_size
        # Guess until the first calibration: ~53 deg horizontal field of view, centred.
        f = float(max(w, h))
        self._K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]], np.float64)
        self._dist = np.zeros(MODELS_BY_NAME[self.model].n_coeffs)
        if self.dup_px is None:
            self.dup_px = 0.05 * math.hypot(w, h)
        self._planner = ViewPlanner(self.board, self.image_size, self.grid, MODELS_BY_NAME[self.model])
        self._hint = self._choose_hint()

    # --- public ----------------------------------------------------------------------------

    @property
    def n_cells(self) -> int:
        return self._planner.n_cells

    @property
    def camera_matrix(self) -> F64:
        """Current K: the latest calibration, or the initial guess before `min_views`."""
        return self._K.copy()

    @property
    def last_detection(self) -> Detection | None:
        """The board found in the last offered frame (for drawing its corners), or None."""
        return self._prev

    @property
    def sigmas(self) -> dict[str, float]:
        """Std devs of fx fy cx cy: of the fit `result()` returns once there is one, else of the
        running fit (empty before `min_views`)."""
        if self._final is not None:
            return {n: float(self._final.std_devs[n]) for n in SIGMA_NAMES}
        return dict(self._sigmas)

    @property
    def n_used(self) -> int | None:
        """Views the written fit uses (outliers rejected); None before it is run."""
        return None if self._final is None else len(self._final.views)

    @property
    def done(self) -> bool:
        """The written fit uses at least `done_views` views and meets the target (module docstring)."""
        final = self._final
        return (
            final is not None
            and len(final.views) >= self.done_views
            and all(final.std_devs[n] <= self.target_sigma_px for n in SIGMA_NAMES)
        )

    @property
    def unreachable(self) -> list[str]:
        """The poses hinted for `hint_patience_s` without a capture, in words (no longer hinted)."""
        return [f"{self._cell_name(c)}, {TILT_BINS[t]}" for c, t in sorted(self._unreachable)]

    def coverage(self) -> NDArray[np.int64]:
        """(cells, tilt bins) count of kept views."""
        cov = np.zeros((self.n_cells, len(TILT_BINS)), np.int64)
        for v in self.views:
            cov[v.cell, v.tilt] += 1
        return cov

    def offer(self, image: NDArray[np.generic], t_us: int) -> Feedback:
        """Look at one live frame; capture it when still, sharp and novel (module docstring)."""
        if self.fast_detect and self.board.kind == "chessboard" and not self._maybe_board(image):
            det = None
        else:
            det = detect(image, self.board, name=f"t{t_us}")
        return self.offer_detection(det, t_us)

    def offer_detection(self, det: Detection | None, t_us: int) -> Feedback:
        """`offer` after detection (for callers that detect themselves, and tests)."""
        prev, self._prev = self._prev, det
        prev_t, self._prev_t = self._prev_t, int(t_us)
        if det is None:
            return self._feedback(t_us, None, reason="board not found")
        if det.image_size != self.image_size:
            raise CalibrationError(
                f"frame size {det.image_size} differs from the session's {self.image_size}"
            )
        motion = self._motion(prev, det)
        blur = self._blur(motion, None if prev_t is None else int(t_us) - prev_t)
        still = blur is not None and blur < self.still_px
        ew = det.edge_width_px
        sharp = not math.isfinite(ew) or ew <= self.max_edge_width_px
        kw = _FrameState(motion, still, sharp, blur)
        if prev is not None and prev_t is not None:  # the board in view since the previous frame
            self._check_hint_patience(min(int(t_us) - prev_t, 1_000_000))
        if self.done:
            return self._feedback(t_us, det, reason="target uncertainty reached", state=kw)
        if det.n < 6:
            return self._feedback(t_us, det, reason=f"only {det.n} corners seen", state=kw)
        if motion is None or blur is None:
            return self._feedback(t_us, det, reason="board appeared: hold it still", state=kw)
        if not still:
            what = "smear" if self.exposure_us else "motion"
            return self._feedback(
                t_us, det, reason=f"moving ({what} {blur:.1f} px > {self.still_px:g} px)", state=kw
            )
        if not sharp:
            why = f"blurred (edge width {ew:.1f} px > {self.max_edge_width_px:g} px)"
            return self._feedback(t_us, det, reason=why, state=kw)
        view = self._make_view(det, t_us)
        why_not = self._redundant(view)
        if why_not:
            return self._feedback(t_us, det, reason=why_not, state=kw)
        self.views.append(view)
        log.info(
            "captured view %d: cell %s, %s (%.0f, %.0f deg)",
            len(self.views),
            self._cell_name(view.cell),
            TILT_BINS[view.tilt],
            *view.angles,
        )
        self.view_errors.append(math.nan)
        if len(self.views) >= self.min_views:
            self._recalibrate()
        self._judge()
        self._set_hint()
        return self._feedback(t_us, det, reason=f"captured view {len(self.views)}", captured=True, state=kw)

    def drop_view(self, index: int) -> None:
        """Forget kept view `index` (0-based; the technician judged it bad): re-fit and re-hint."""
        if not 0 <= index < len(self.views):
            raise CalibrationError(f"no view {index + 1}: the session holds {len(self.views)}")
        del self.views[index]
        del self.view_errors[index]
        log.info("dropped view %d; %d left", index + 1, len(self.views))
        if len(self.views) >= self.min_views:
            self._recalibrate()
        else:
            self._sigmas, self._rms = {}, None
            self.view_errors = [math.nan] * len(self.views)
        self._judge()
        self._set_hint()

    def view_list(self) -> list[dict[str, Any]]:
        """The kept views for a display: where, which tilt, RMS error (None before a calibration)."""
        return [
            {
                "index": i,
                "t_us": v.t_us,
                "cell": self._cell_name(v.cell),
                "tilt": TILT_BINS[v.tilt],
                "rms_px": None if not math.isfinite(e) else round(e, 4),
            }
            for i, (v, e) in enumerate(zip(self.views, self.view_errors, strict=True))
        ]

    def hint_outline(self) -> list[list[float]] | None:
        """Image corners (4 x [x, y]) of the board at the next pose the hint asks for (a ghost
        outline to draw), or None when there is no hint or the session is done."""
        if self._hint is None or self.done:
            return None
        depth = self._planner.depth(self._K, [v.tvec for v in self.views])
        pose = self._synthetic_pose(self._hint.cell, self._hint.tilt, depth)
        if pose is None:
            return None
        outline = self._planner.outline()
        p = cv2.projectPoints(outline, pose[0], pose[1], self._K, self._dist)[0].reshape(-1, 2)
        return [[round(float(x), 1), round(float(y), 1)] for x, y in p]

    def result(self, camera: str = "cam0", model: str | None = None) -> IntrinsicsResult:
        """The full calibration of the kept views (outlier rejection, warnings, per-view data):
        the fit `done` judged, when the session ran it for these views and this model."""
        if len(self.views) < 3:
            raise CalibrationError(
                f"camera {camera}: only {len(self.views)} view(s) captured; need at least 3 to calibrate"
            )
        if self._final is not None and (model is None or model == self.model):
            return self._final.model_copy(update={"camera": camera})
        return calibrate_intrinsics(
            [v.det for v in self.views], self.board, camera=camera, model=model or self.model
        )

    def hint_text(self) -> str:
        """The next hint in words (or that the session is done)."""
        if self.done:
            return "target uncertainty reached: you can stop"
        if self._hint is None:
            return "show the board anywhere"
        return f"move the board to the {self._cell_name(self._hint.cell)} and " + _TILT_TEXT[
            TILT_BINS[self._hint.tilt]
        ].format(deg=TILT_DEG, flat=FLAT_DEG)

    # --- per frame ----------------------------------------------------------------------------

    def _maybe_board(self, image: NDArray[np.generic]) -> bool:
        """Pre-test for live frames: does the classic detector find the chessboard? (module docstring)"""
        img = np.asarray(image)
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
        if img.dtype != np.uint8:
            return True  # let detect() normalise and decide
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        ok, _ = cv2.findChessboardCorners(np.ascontiguousarray(img), self.board.inner_corners, flags=flags)
        return bool(ok)

    def _blur(self, motion: float | None, dt_us: int | None) -> float | None:
        """Smear in one exposure from the motion over `dt_us` (module docstring, step 2)."""
        if motion is None or self.exposure_us is None:
            return motion
        if dt_us is None or dt_us <= 0:
            return None
        return motion * min(1.0, self.exposure_us / dt_us)

    @staticmethod
    def _motion(prev: Detection | None, det: Detection) -> float | None:
        if prev is None:
            return None
        common, ia, ib = np.intersect1d(prev.ids, det.ids, return_indices=True)
        if common.size < 4:
            return None
        return float(np.linalg.norm(prev.image_points[ia] - det.image_points[ib], axis=1).max())

    def _pose(self, det: Detection) -> tuple[F64, F64]:
        ok, rvec, tvec = cv2.solvePnP(det.object_points, det.image_points, self._K, self._dist)
        if not ok:
            raise CalibrationError(f"{det.name}: PnP failed")
        return np.asarray(rvec, np.float64).ravel(), np.asarray(tvec, np.float64).ravel()

    def _cell_of(self, det: Detection) -> int:
        return self._planner.cell_of_points(det.image_points)

    def _cell_name(self, cell: int) -> str:
        return self._planner.cell_name(cell)

    def _make_view(self, det: Detection, t_us: int) -> _View:
        rvec, tvec = self._pose(det)
        angles = tilt_angles(rvec)
        return _View(det, t_us, rvec, tvec, self._cell_of(det), tilt_bin(angles), angles)

    def _redundant(self, view: _View) -> str:
        """Why the view adds no coverage ("" when it does)."""
        same_bin = [v for v in self.views if (v.cell, v.tilt) == (view.cell, view.tilt)]
        if len(same_bin) >= self.max_per_bin:
            return f"{self._cell_name(view.cell)} / {TILT_BINS[view.tilt]} already has {len(same_bin)} views"
        assert self.dup_px is not None
        for i, v in enumerate(self.views):
            common, ia, ib = np.intersect1d(v.det.ids, view.det.ids, return_indices=True)
            if common.size < 4:
                continue
            dist = float(np.linalg.norm(v.det.image_points[ia] - view.det.image_points[ib], axis=1).mean())
            dang = math.hypot(v.angles[0] - view.angles[0], v.angles[1] - view.angles[1])
            if dist < self.dup_px and dang < self.dup_deg:
                return f"near-duplicate of view {i + 1} ({dist:.0f} px, {dang:.0f} deg apart)"
        return ""

    # --- calibration and uncertainty ------------------------------------------------------------

    def _judge(self) -> None:
        """Run the fit `result()` returns (and a caller writes) once `done_views` are kept."""
        self._final = None
        if len(self.views) < max(self.done_views, 3):
            return
        try:
            self._final = calibrate_intrinsics(
                [v.det for v in self.views], self.board, camera="guided", model=self.model
            )
        except CalibrationError as exc:
            log.warning("guided session: full calibration of %d views failed: %s", len(self.views), exc)
            return
        log.debug(
            "guided session: written fit uses %d of %d views, sigmas %s",
            len(self._final.views),
            len(self.views),
            {k: round(self._final.std_devs[k], 3) for k in SIGMA_NAMES},
        )

    def _recalibrate(self) -> None:
        """Re-fit the fast model on the kept views; update K, sigmas and the views' poses/bins."""
        lens = MODELS_BY_NAME[self.model]
        try:
            fit = fit_model([v.det for v in self.views], self.image_size, lens)
        except CalibrationError as exc:
            log.warning("guided session: calibration of %d views failed: %s", len(self.views), exc)
            return
        self._K, self._dist, self._rms = fit.K, fit.dist, fit.rms
        self._sigmas = {n: float(fit.std[i]) for i, n in enumerate(SIGMA_NAMES)}
        self.view_errors = [float(e) for e in np.asarray(fit.per_view, np.float64).ravel()]
        for v, rv, tv in zip(self.views, fit.rvecs, fit.tvecs, strict=True):
            v.rvec, v.tvec = rv, tv
            v.angles = tilt_angles(rv)
            v.tilt = tilt_bin(v.angles)
        log.debug(
            "guided session: %d views, RMS %.3f px, sigmas %s",
            len(self.views),
            fit.rms,
            {k: round(s, 3) for k, s in self._sigmas.items()},
        )

    def _set_hint(self) -> None:
        """Choose the next hint; a pose just captured starts its patience again."""
        if self.views:
            self._waited_us.pop((self.views[-1].cell, self.views[-1].tilt), None)
        self._hint = self._choose_hint()

    def _check_hint_patience(self, dt_us: int) -> None:
        """Give up on a pose hinted for `hint_patience_s` in all without a capture there (module
        docstring); `dt_us`: the frame time since the previous frame with the board in view."""
        if self._hint is None or self.done:
            return
        pose = (self._hint.cell, self._hint.tilt)
        self._waited_us[pose] = self._waited_us.get(pose, 0) + max(0, dt_us)
        if self._waited_us[pose] < self.hint_patience_s * 1e6:
            return
        self._unreachable.add(pose)
        log.info(
            "guided session: no capture at %s, %s for %.0f s; not hinted again",
            self._cell_name(pose[0]),
            TILT_BINS[pose[1]],
            self.hint_patience_s,
        )
        if len(self._unreachable) >= self.n_cells * len(TILT_BINS):
            self._unreachable.clear()  # every pose given up on: start over rather than hint nothing
        self._set_hint()

    def _synthetic_pose(self, cell: int, tilt: int, depth: float) -> tuple[F64, F64] | None:
        """A board pose in the bin at the current intrinsics (ViewPlanner.synthetic_pose)."""
        return self._planner.synthetic_pose(self._K, self._dist, cell, tilt, depth)

    def _choose_hint(self) -> Candidate | None:
        """The bin to show next (`calibration.view_planning`); None before anything can be said."""
        cov = self.coverage()
        if self.hint_method == "emptiest":
            return self._planner.emptiest(cov, self._unreachable)
        views = [(v.det.object_points, v.rvec, v.tvec) for v in self.views]
        return self._planner.best_information(self._K, self._dist, views, self._rms, cov, self._unreachable)

    # --- feedback ----------------------------------------------------------------------------

    def _feedback(
        self,
        t_us: int,
        det: Detection | None,
        reason: str,
        state: _FrameState | None = None,
        captured: bool = False,
    ) -> Feedback:
        motion, still, sharp, blur = state if state is not None else (None, False, False, None)
        cov = self.coverage()
        hint = self._hint
        return Feedback(
            t_us=int(t_us),
            detected=det is not None,
            n_corners=det.n if det is not None else 0,
            motion_px=motion,
            blur_px=blur,
            still=still,
            edge_width_px=(
                det.edge_width_px if det is not None and math.isfinite(det.edge_width_px) else None
            ),
            sharp=sharp,
            captured=captured,
            reason=reason,
            n_views=len(self.views),
            n_used=self.n_used,
            coverage=cov.tolist(),
            cells_covered=float((cov.sum(axis=1) > 0).mean()),
            tilts_covered=float((cov.sum(axis=0) > 0).mean()),
            next_hint=self.hint_text(),
            hint_cell=self._cell_name(hint.cell) if hint is not None and not self.done else "",
            hint_tilt=TILT_BINS[hint.tilt] if hint is not None and not self.done else "",
            sigmas=self.sigmas,
            rms_px=self._rms,
            done=self.done,
        )
