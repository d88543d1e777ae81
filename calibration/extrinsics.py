# ruff: noqa: N802, N803, N806  (K, R, T, J follow the notation of the calibration literature)
"""Rig extrinsics: every camera's pose in one rig frame from simultaneous board views.

A "view" is one trigger pulse: the board seen at the same instant by several cameras. Each
(camera, view) detection gives the board's pose in that camera by PnP; chaining them through views
shared with already-posed cameras initialises every camera's pose relative to the reference
camera (the rig frame). Then one Levenberg-Marquardt problem (scipy.optimize.least_squares,
trust-region) refines all camera poses and all board poses together on the reprojection error of
every corner in every camera, with each camera's intrinsics held fixed at their calibrated values.
Parameter uncertainty is sigma^2 (J^T J)^-1 at the solution (sigma^2 the residual variance) plus
the intrinsics' own uncertainty propagated to first order: holding intrinsics fixed makes the
extrinsics inherit their errors, which sigma^2 (J^T J)^-1 alone misses (it understated the
extrinsic sigma 5-9x). Each camera's intrinsic covariance is rebuilt from its calibration views
(Schur complement of the view poses in the normal matrix, as OpenCV computes its std devs, but
keeping the correlations), and the solution's sensitivity to the intrinsics,
dx/dtheta = -(J^T J)^-1 J^T J_theta, carries it into the extrinsic covariance.

Convention: a camera's (R, t) maps rig coordinates into that camera, x_cam = R x_rig + t; the
reference camera has R = I, t = 0; t in metres. The camera centre in the rig is -R^T t.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel
from scipy.optimize import OptimizeResult, least_squares
from scipy.sparse import lil_matrix

from calibration.boards import BoardSpec, Detection
from calibration.errors import CalibrationError
from calibration.intrinsics import IntrinsicsResult
from calibration.lens_models import DIST_NAMES

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
#: Initial relative-pose estimates further than this from the consensus are dropped (wrong corner order).
_INIT_OUTLIER_DEG = 10.0


class CameraPose(BaseModel):
    """One camera's pose in the rig frame with one-sigma uncertainties."""

    camera: str
    R: list[list[float]]
    t: list[float]
    rvec: list[float]
    center_m: list[float]
    rot_std_deg: list[float]
    t_std_m: list[float]
    rms_px: float
    n_views: int


class RigResult(BaseModel):
    reference: str
    board: str
    cameras: list[CameraPose]
    rms_px: float
    per_view_rms_px: dict[str, float]
    n_views: int
    warnings: list[str] = []
    overlaps: dict[str, list[str]] = {}
    """Per camera, the cameras it saw the board together with in a view the solve used (Kalibr's
    `cam_overlaps`)."""

    def pose(self, camera: str) -> tuple[F64, F64]:
        """(R, t) of `camera`; CalibrationError when it is not in the rig."""
        for c in self.cameras:
            if c.camera == camera:
                return np.asarray(c.R, np.float64), np.asarray(c.t, np.float64)
        raise CalibrationError(f"camera {camera!r} not in the rig ({[c.camera for c in self.cameras]})")

    def relative(self, a: str, b: str) -> tuple[F64, F64]:
        """(R, t) taking camera a's coordinates into camera b's (what cv2.stereoCalibrate returns)."""
        Ra, ta = self.pose(a)
        Rb, tb = self.pose(b)
        R = Rb @ Ra.T
        return R, tb - R @ ta


def _to_T(rvec: F64, tvec: F64) -> F64:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]
    T[:3, 3] = np.asarray(tvec, np.float64).ravel()
    return T


def _from_T(T: F64) -> tuple[F64, F64]:
    return np.asarray(cv2.Rodrigues(T[:3, :3])[0], np.float64).ravel(), T[:3, 3].copy()


def _inv(T: F64) -> F64:
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def _rot_angle_deg(Ra: F64, Rb: F64) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return math.degrees(math.acos(float(np.clip(c, -1.0, 1.0))))


def _mean_T(Ts: Sequence[F64]) -> F64:
    """Chordal mean of rotations (SVD projection of the summed matrices), median of translations."""
    U, _, Vt = np.linalg.svd(sum(T[:3, :3] for T in Ts))
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.median(np.stack([T_[:3, 3] for T_ in Ts]), axis=0)
    return T


def _pnp(d: Detection, intr: IntrinsicsResult) -> F64:
    K, dist = intr.camera_matrix(), intr.dist_coeffs()
    ok, rvec, tvec = cv2.solvePnP(d.object_points, d.image_points, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibrationError(f"camera {intr.camera}, view {d.name}: PnP failed")
    rvec, tvec = cv2.solvePnPRefineLM(d.object_points, d.image_points, K, dist, rvec, tvec)
    return _to_T(np.asarray(rvec, np.float64).ravel(), np.asarray(tvec, np.float64).ravel())


def _flipped(d: Detection) -> Detection:
    """The same chessboard detection with the corner order rotated by 180 degrees."""
    return Detection(
        d.name, d.image_size, d.image_points[::-1].copy(), d.ids, d.object_points, d.edge_width_px
    )


def _free_intrinsics(intr: IntrinsicsResult) -> list[int]:
    """Columns of cv2.projectPoints' jacobian (after rvec, tvec) of the calibrated free parameters:
    fx fy cx cy, then the distortion terms that the lens model left free."""
    n_dist = intr.dist_coeffs().size
    dist_idx = [4 + i for i, n in enumerate(DIST_NAMES) if n in intr.std_devs and i < n_dist]
    return [0, 1, 2, 3, *dist_idx]


def _project_jac(obj: F64, rvec: F64, tvec: F64, K: F64, dist: F64) -> tuple[F64, F64]:
    """(projections (N, 2), jacobian (2N, 10 + n_dist)) with OpenCV's column order."""
    proj, jac = cv2.projectPoints(obj.reshape(-1, 1, 3), rvec, tvec, K, dist)
    return np.asarray(proj, np.float64).reshape(-1, 2), np.asarray(jac, np.float64)


def intrinsic_covariance(intr: IntrinsicsResult, board: BoardSpec) -> F64:
    """Full covariance of a camera's free intrinsics (see `_free_intrinsics`), sigma^2 S^-1 with S
    the Schur complement of the view poses in the calibration's normal matrix."""
    K, dist = intr.camera_matrix(), intr.dist_coeffs()
    cols = _free_intrinsics(intr)
    obj_all = board.object_points()
    n_i = len(cols)
    S = np.zeros((n_i, n_i))
    n_obs = 0
    for v in intr.views:
        obj = obj_all[np.asarray(v.ids, np.int64)]
        _, jac = _project_jac(obj, np.asarray(v.rvec), np.asarray(v.tvec), K, dist)
        Jp, Ji = jac[:, :6], jac[:, 6:][:, cols]
        A, B, C = Ji.T @ Ji, Ji.T @ Jp, Jp.T @ Jp
        S += A - B @ np.linalg.solve(C, B.T)
        n_obs += jac.shape[0]
    dof = max(n_obs - n_i - 6 * len(intr.views), 1)
    sigma2 = intr.rms_px**2 * n_obs / dof
    return np.asarray(sigma2 * np.linalg.pinv(S), np.float64)


Views = Mapping[str, Mapping[str, Detection]]
#: Views as the stages use them: each keeps the detections that take part, two or more per view.
_Used = dict[str, dict[str, Detection]]


def calibrate_rig(
    intrinsics: Mapping[str, IntrinsicsResult],
    views: Views,
    board: BoardSpec,
    reference: str | None = None,
) -> RigResult:
    """Poses of all cameras in the rig frame of `reference` (default: the first camera).

    `views` maps a view id (pulse index, file stem) to the detections of the cameras that saw the
    board at that instant. Views seen by a single camera only add nothing and are skipped.
    """
    cams = _reference_first(intrinsics, reference)
    warnings: list[str] = []
    used = _shared_views(views, intrinsics, cams, warnings)
    chain = _PoseChain(intrinsics, board, used, _board_poses_by_pnp(used, intrinsics), warnings)
    chain.pose_all(cams)
    problem = _RigProblem.build(cams, chain.views_left(), intrinsics)
    x0 = problem.initial_parameters(chain.T_c0, chain.T_cb)
    sol = _refine_jointly(problem, x0, warnings)
    cov = _pose_covariance(problem, sol, intrinsics, board)
    per_cam_sq, per_view_sq = problem.squared_errors(sol.fun)
    cam_T, _ = problem.unpack(sol.x)
    poses = [_camera_pose(i, c, cam_T[i], cov, per_cam_sq[i]) for i, c in enumerate(cams)]
    if len(problem.vids) < 5:
        warnings.append(f"only {len(problem.vids)} shared views; the extrinsics rest on few board poses")
    for w in warnings:  # returned in .warnings: the caller reports them, once
        log.info("%s", w)
    r = sol.fun
    return RigResult(
        reference=cams[0],
        board=str(board),
        cameras=poses,
        rms_px=float(math.sqrt(float(r @ r) / (problem.n_residuals / 2))),
        per_view_rms_px={
            problem.vids[j]: float(math.sqrt(np.concatenate(v).mean())) for j, v in per_view_sq.items()
        },
        n_views=len(problem.vids),
        warnings=warnings,
        overlaps={c: sorted({o for v in used.values() if c in v for o in v if o != c}) for c in cams},
    )


def _reference_first(intrinsics: Mapping[str, IntrinsicsResult], reference: str | None) -> list[str]:
    """The cameras, reference first: its frame is the rig frame."""
    cams = list(intrinsics)
    if len(cams) < 2:
        raise CalibrationError(f"rig calibration needs at least 2 cameras, got {cams}")
    ref = reference or cams[0]
    if ref not in intrinsics:
        raise CalibrationError(f"reference camera {ref!r} has no intrinsics (have {cams})")
    return [ref] + [c for c in cams if c != ref]


def _shared_views(
    views: Views, intrinsics: Mapping[str, IntrinsicsResult], cams: list[str], warnings: list[str]
) -> _Used:
    """Views that show the board (6+ corners) in two or more calibrated cameras."""
    used = {
        vid: {c: d for c, d in dets.items() if c in intrinsics and d.n >= 6} for vid, dets in views.items()
    }
    used = {vid: dets for vid, dets in used.items() if len(dets) >= 2}
    if not used:
        raise CalibrationError(f"no view shows the board in two or more of the cameras {cams}")
    unknown = sorted({c for dets in views.values() for c in dets} - set(intrinsics))
    if unknown:
        warnings.append(f"detections of cameras without intrinsics ignored: {unknown}")
    return used


def _board_poses_by_pnp(
    used: _Used, intrinsics: Mapping[str, IntrinsicsResult]
) -> dict[tuple[str, str], F64]:
    """The board's pose in each camera of each view, T_cb[camera, view]."""
    T_cb: dict[tuple[str, str], F64] = {}
    for vid, dets in used.items():
        for c, d in dets.items():
            T_cb[c, vid] = _pnp(d, intrinsics[c])
    return T_cb


@dataclass
class _PoseChain:
    """Initial camera poses relative to the reference (T_c0), grown through views shared with
    cameras already posed. A view whose estimate disagrees with the consensus has its chessboard
    corner order flipped when that agrees, else it is dropped (`used` and `T_cb` are updated)."""

    intrinsics: Mapping[str, IntrinsicsResult]
    board: BoardSpec
    used: _Used
    T_cb: dict[tuple[str, str], F64]
    warnings: list[str]
    T_c0: dict[str, F64] = field(default_factory=dict)

    def pose_all(self, cams: list[str]) -> None:
        """Pose every camera; CalibrationError names those that share no view with the chain."""
        self.T_c0 = {cams[0]: np.eye(4)}
        progress = True
        while progress and len(self.T_c0) < len(cams):
            progress = False
            for c in cams:
                if c not in self.T_c0 and self._pose(c):
                    progress = True
        missing = [c for c in cams if c not in self.T_c0]
        if missing:
            raise CalibrationError(
                f"cameras {missing} share no board view with the reference chain from {cams[0]}"
            )

    def views_left(self) -> _Used:
        """The views that still show the board in two or more cameras after the drops."""
        return {vid: dets for vid, dets in self.used.items() if len(dets) >= 2}

    def _pose(self, c: str) -> bool:
        """Pose camera `c` from its views with posed cameras; False when it has none yet."""
        est = self._estimates(c)
        if not est:
            return False
        mean = _mean_T([T for _, T in est])
        for vid, T in est:
            ang = _rot_angle_deg(T[:3, :3], mean[:3, :3])
            if ang > _INIT_OUTLIER_DEG:
                self._flip_or_drop(c, vid, ang, mean)
        good = [T for _, T in self._estimates(c)]
        self.T_c0[c] = _mean_T(good) if good else mean
        return True

    def _estimates(self, c: str) -> list[tuple[str, F64]]:
        """Per view of `c`: its pose through the first posed camera of that view."""
        est: list[tuple[str, F64]] = []
        for vid, dets in self.used.items():
            if c not in dets:
                continue
            p = next((q for q in dets if q in self.T_c0), None)
            if p is not None:
                est.append((vid, self._through(c, vid, p, self.T_cb[c, vid])))
        return est

    def _through(self, c: str, vid: str, p: str, T_cb_c: F64) -> F64:
        return T_cb_c @ _inv(self.T_cb[p, vid]) @ self.T_c0[p]

    def _flip_or_drop(self, c: str, vid: str, ang: float, mean: F64) -> None:
        d = self.used[vid][c]
        flip_T = (
            _pnp(_flipped(d), self.intrinsics[c])
            if d.is_complete(self.board) and self.board.kind == "chessboard"
            else None
        )
        p = next(p for p in self.used[vid] if p in self.T_c0)
        if (
            flip_T is not None
            and _rot_angle_deg(self._through(c, vid, p, flip_T)[:3, :3], mean[:3, :3]) <= _INIT_OUTLIER_DEG
        ):
            log.info("camera %s, view %s: corner order flipped to match the rig", c, vid)
            self.used[vid][c] = _flipped(d)
            self.T_cb[c, vid] = flip_T
        else:
            self.warnings.append(
                f"camera {c}, view {vid}: pose disagrees with the others by {ang:.1f} deg; dropped"
            )
            del self.used[vid][c]


@dataclass
class _Obs:
    cam: int
    view: int
    det: Detection


@dataclass
class _RigProblem:
    """The joint refinement. Parameters: (rvec, tvec) of every camera but the reference, then of
    every board pose; residuals: projected minus detected, per corner of every observation."""

    cams: list[str]
    vids: list[str]
    obs: list[_Obs]
    Ks: list[F64]
    dists: list[F64]

    @classmethod
    def build(cls, cams: list[str], used: _Used, intrinsics: Mapping[str, IntrinsicsResult]) -> _RigProblem:
        vids = list(used)
        obs = [_Obs(cams.index(c), i, d) for i, vid in enumerate(vids) for c, d in used[vid].items()]
        Ks = [intrinsics[c].camera_matrix() for c in cams]
        dists = [intrinsics[c].dist_coeffs() for c in cams]
        return cls(cams, vids, obs, Ks, dists)

    @property
    def n_cams(self) -> int:
        """Cameras with free poses (all but the reference)."""
        return len(self.cams) - 1

    @property
    def n_residuals(self) -> int:
        return sum(2 * o.det.n for o in self.obs)

    def initial_parameters(self, T_c0: Mapping[str, F64], T_cb: Mapping[tuple[str, str], F64]) -> F64:
        """Chained camera poses; board poses in the rig frame as the mean over the cameras that saw them."""
        used: dict[int, list[str]] = {}
        for o in self.obs:
            used.setdefault(o.view, []).append(self.cams[o.cam])
        T_0b = [_mean_T([_inv(T_c0[c]) @ T_cb[c, vid] for c in used[j]]) for j, vid in enumerate(self.vids)]
        return np.concatenate(
            [np.concatenate(_from_T(T_c0[c])) for c in self.cams[1:]]
            + [np.concatenate(_from_T(T)) for T in T_0b]
        )

    def unpack(self, x: F64) -> tuple[list[F64], list[F64]]:
        """(camera poses, reference first; board poses) as 4x4 transforms."""
        nc = self.n_cams
        cam_T = [np.eye(4)] + [_to_T(x[6 * i : 6 * i + 3], x[6 * i + 3 : 6 * i + 6]) for i in range(nc)]
        off = 6 * nc
        view_T = [
            _to_T(x[off + 6 * j : off + 6 * j + 3], x[off + 6 * j + 3 : off + 6 * j + 6])
            for j in range(len(self.vids))
        ]
        return cam_T, view_T

    def residuals(self, x: F64) -> F64:
        cam_T, view_T = self.unpack(x)
        out = []
        for o in self.obs:
            rvec, tvec = _from_T(cam_T[o.cam] @ view_T[o.view])
            proj, _ = cv2.projectPoints(
                o.det.object_points.reshape(-1, 1, 3), rvec, tvec, self.Ks[o.cam], self.dists[o.cam]
            )
            out.append((proj.reshape(-1, 2) - o.det.image_points).ravel())
        return np.concatenate(out)

    def sparsity(self, n_params: int) -> lil_matrix:
        """Which parameters each residual depends on: its camera's pose and its board pose."""
        nc = self.n_cams
        sparsity = lil_matrix((self.n_residuals, n_params), dtype=int)
        row = 0
        for o in self.obs:
            rows = slice(row, row + 2 * o.det.n)
            if o.cam > 0:
                sparsity[rows, 6 * (o.cam - 1) : 6 * o.cam] = 1
            sparsity[rows, 6 * nc + 6 * o.view : 6 * nc + 6 * o.view + 6] = 1
            row += 2 * o.det.n
        return sparsity

    def intrinsic_jacobian(self, ci: int, cols: list[int], x: F64) -> F64:
        """d residuals / d (free intrinsics of camera `ci`) at x; zero rows for other cameras."""
        cam_T, view_T = self.unpack(x)
        J_theta = np.zeros((self.n_residuals, len(cols)))
        row = 0
        for o in self.obs:
            n2 = 2 * o.det.n
            if o.cam == ci:
                rvec, tvec = _from_T(cam_T[o.cam] @ view_T[o.view])
                _, jac = _project_jac(o.det.object_points, rvec, tvec, self.Ks[ci], self.dists[ci])
                J_theta[row : row + n2] = jac[:, 6:][:, cols]
            row += n2
        return J_theta

    def squared_errors(self, r: F64) -> tuple[dict[int, list[F64]], dict[int, list[F64]]]:
        """Squared corner errors of the residuals `r`, grouped per camera and per view."""
        r2 = r.reshape(-1, 2)
        per_cam_sq: dict[int, list[F64]] = {i: [] for i in range(len(self.cams))}
        per_view_sq: dict[int, list[F64]] = {j: [] for j in range(len(self.vids))}
        row = 0
        for o in self.obs:
            sq = (r2[row : row + o.det.n] ** 2).sum(axis=1)
            per_cam_sq[o.cam].append(sq)
            per_view_sq[o.view].append(sq)
            row += o.det.n
        return per_cam_sq, per_view_sq


def _refine_jointly(problem: _RigProblem, x0: F64, warnings: list[str]) -> OptimizeResult:
    """Levenberg-Marquardt-style trust-region refinement of all poses on the reprojection error."""
    sol = least_squares(
        problem.residuals,
        x0,
        jac_sparsity=problem.sparsity(x0.size),
        method="trf",
        x_scale="jac",
        xtol=1e-10,
        ftol=1e-10,
        gtol=1e-10,
        max_nfev=500,
    )
    if not sol.success:
        warnings.append(f"joint refinement did not converge: {sol.message}")
    dof = problem.n_residuals - x0.size
    if dof <= 0:
        raise CalibrationError(
            f"rig problem underdetermined: {problem.n_residuals} residuals for {x0.size} parameters"
        )
    return sol


def _pose_covariance(
    problem: _RigProblem, sol: OptimizeResult, intrinsics: Mapping[str, IntrinsicsResult], board: BoardSpec
) -> F64:
    """sigma^2 (J^T J)^-1 plus each camera's intrinsic covariance propagated (module docstring)."""
    r = sol.fun
    sigma2 = float(r @ r) / (problem.n_residuals - sol.x.size)
    J = sol.jac.toarray() if hasattr(sol.jac, "toarray") else np.asarray(sol.jac)
    JtJ = J.T @ J
    try:
        cov = sigma2 * np.linalg.inv(JtJ)
    except np.linalg.LinAlgError as exc:
        raise CalibrationError("rig problem is degenerate (singular normal matrix); add views") from exc
    JtJ_inv = np.linalg.inv(JtJ)
    for ci, c in enumerate(problem.cams):
        intr = intrinsics[c]
        if not intr.views:
            continue
        J_theta = problem.intrinsic_jacobian(ci, _free_intrinsics(intr), sol.x)
        sens = JtJ_inv @ (J.T @ J_theta)
        cov = cov + sens @ intrinsic_covariance(intr, board) @ sens.T
    return np.asarray(cov, np.float64)


def _camera_pose(i: int, camera: str, T: F64, cov: F64, sq: list[F64]) -> CameraPose:
    """Camera `i`'s refined pose, its one-sigma uncertainties and reprojection RMS."""
    rvec, tvec = _from_T(T)
    if i == 0:
        rstd, tstd = np.zeros(3), np.zeros(3)
    else:
        var = np.diag(cov)[6 * (i - 1) : 6 * i]
        rstd, tstd = np.degrees(np.sqrt(var[:3])), np.sqrt(var[3:])
    R = T[:3, :3]
    sq_all = np.concatenate(sq) if sq else np.zeros(1)
    pose = CameraPose(
        camera=camera,
        R=R.tolist(),
        t=tvec.tolist(),
        rvec=rvec.tolist(),
        center_m=(-R.T @ tvec).tolist(),
        rot_std_deg=rstd.tolist(),
        t_std_m=tstd.tolist(),
        rms_px=float(math.sqrt(sq_all.mean())),
        n_views=len(sq),
    )
    log.info(
        "camera %s: t=%s m (std %s), RMS %.3f px", camera, np.round(tvec, 4), np.round(tstd, 5), pose.rms_px
    )
    return pose
